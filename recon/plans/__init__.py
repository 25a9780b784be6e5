"""What each stage decides, with the reason it prints: `plans.training` for the train stage (and the profiler and
benchmarks, which must run the very step the stage runs), `plans.mesh` for the mesh stage."""
