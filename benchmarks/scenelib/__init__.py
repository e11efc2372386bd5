"""The repository's own scenes and measures, for benchmarks/ and tests/: the real-model scenes of
models/real/ as MuJoCo C runs them (``real_scenes``), the resting-contact stability measures
(``stability``) and the soak's checkpoints (``checkpoint``). They read models/ from the source
tree, so they are not part of the installed package."""
