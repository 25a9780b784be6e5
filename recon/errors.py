"""User-facing errors: the CLI prints these as one paragraph, without a traceback."""
from __future__ import annotations


class ReconError(Exception):
    """An error the user can fix; str() is the whole message (what is wrong, which file, what to do)."""


class InputError(ReconError):
    """The input (photos, poses, a scene file) is unusable as given."""


class ConfigError(ReconError):
    """A preset, an option or a `--set` override is invalid."""
