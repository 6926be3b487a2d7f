"""The SUMO side of the twin: networks, demand, the libsumo session, lane-to-cell geometry, and
the live traffic source that advances SUMO in lockstep with the swarms (Sec. IV-B).

Nothing outside this package imports SUMO; the CLI imports it lazily.
"""
