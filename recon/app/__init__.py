"""The faces: command line, Python API, batch (Ray), bench, profiling, viewer, novel-view renders, exports, progress
display. They call the runner; none is a second pipeline."""
