"""Training the Q-network: pretraining (Sec. III-A) with its recipes, and the learning curve of
its snapshots on validation seeds. Above the experiment runner, which both use; the network,
the replay buffer and the Double DQN update they train live in :mod:`twin.learning`."""
