"""The sim-to-real transfer matrix: learned swarms trained on several kinds of traffic (rows)
evaluated on several scenarios (columns), each cell the learned swarm's R_hat_T against the
best classical swarm's on the same traffic, paired over seeds.

``twin transfer --config configs/transfer.toml`` (:mod:`twin.cli.transfer`). Modules:
:mod:`~twin.transfer.config` (the config), :mod:`~twin.transfer.runner` (tapes, training,
the evaluation sweep), :mod:`~twin.transfer.matrix` (the cells), :mod:`~twin.transfer.report`
(the HTML page and the heatmap).
"""
