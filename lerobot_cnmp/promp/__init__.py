"""The ProMP baseline (Paraschos et al. 2013, through ``movement_primitives``) as a LeRobot policy,
``--policy.type=promp``: its config, the open-loop policy, its processors, ``lerobot-cnmp-fit-promp`` (the
closed-form fit) and the array-level ``ProMPBaseline`` / ``DMPBaseline`` used by the benchmarks."""
