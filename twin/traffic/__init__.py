"""Traffic sources: where the importance map ``T^k`` of every step comes from (Def. 2)."""

from twin.traffic.base import TrafficSource, normalise_importance

__all__ = ["TrafficSource", "normalise_importance"]
