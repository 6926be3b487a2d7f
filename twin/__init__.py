"""twin: a SUMO digital twin patrolled by a learning drone swarm."""

__version__ = "0.1.0"
