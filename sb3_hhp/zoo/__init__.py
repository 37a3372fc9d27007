"""The parts of ``python -m sb3_hhp.train`` (:mod:`sb3_hhp.train`, the RL Zoo entry point) that are not the command line.

- :mod:`sb3_hhp.zoo.config`: the hyperparameter file (where it is, which entry serves an env id, which keys it may
  set) and the ``--env`` check, all refused in one line (:class:`~sb3_hhp.zoo.config.ConfigError`) before training;
- :mod:`sb3_hhp.zoo.experiment`: RL Zoo's experiment manager for HhP (the oracle, the preference database,
  resuming from a checkpoint, the labeling server);
- :mod:`sb3_hhp.zoo.checkpoints`: the latest-checkpoint callback, reading a run folder's checkpoint and the seed of
  a resumed part;
- :mod:`sb3_hhp.zoo.evaluation`: the final evaluation on fresh seeds and the run's summary.

Nothing here is imported by ``import sb3_hhp``; RL Zoo, SB3 and torch are imported where they are used.
"""
