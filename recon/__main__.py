"""`python -m recon ...` runs the command line without installing the package (e.g. from a checkout on a machine
without network, with its dependencies on PYTHONPATH)."""
from recon.app.cli import main

main()
