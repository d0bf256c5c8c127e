"""The DF1 kind's full-duplex master role: one SLC 500 / PLC-5 per port (``duplex = "full"``).

What this package owns: :mod:`.driver`, the asyncio loop around the full-duplex cores
(:mod:`gateway.protocols.df1.full_duplex`): it owns the port, moves the bytes, runs the core's one
timer and turns its verdicts into results.  The unit that polls through it, its plan, config model,
CLI commands and simulators are shared by every role of the kind and stay in :mod:`gateway.kinds.df1`.
"""
