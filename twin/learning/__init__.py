"""The learned swarm's parts (the Q-network, the replay buffer, the Double DQN update,
checkpoints, online learning): the only package besides :mod:`twin.training` that imports
torch. torch's compiler cache (which building an optimizer makes) goes into twin's cache, not
the system's temporary folder: twin writes only into its run folder and its cache."""

import os

from twin.resources import cache_dir

os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", str(cache_dir() / "torch"))
