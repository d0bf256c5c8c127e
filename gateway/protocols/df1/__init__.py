"""Sans-I/O DF1 (full and half duplex) and PCCC for SLC 500 and PLC-5 controllers.

One package per duplex mode, and here what both modes share:

* :mod:`~gateway.protocols.df1.full_duplex` - the full-duplex station in either role: the master's
  data link and its PCCC transactions, the target's responder (1770-6.5.16 chapter 4)
* :mod:`~gateway.protocols.df1.half_duplex` - the half-duplex line master, its schedule, transmitter,
  transactions and the reply to a slave's own messages (1770-6.5.16 chapter 3)

Shared by both modes and every role:

* :mod:`~gateway.protocols.df1.framing` - DLE framing of both duplex modes; its streaming decoder is
  :mod:`~gateway.protocols.df1.framing.decoder`, the checks (BCC / CRC-16) :mod:`~gateway.protocols.df1.checks`
* :mod:`~gateway.protocols.df1.pccc` - PCCC command / reply packets, STS codes, size limits, TNS, and
  the core that answers a PLC's MSG (:mod:`~gateway.protocols.df1.pccc.target`)
* :mod:`~gateway.protocols.df1.address` - SLC 500 logical addresses (``N7:0``, ``T4:3.ACC`` ...);
  :mod:`~gateway.protocols.df1.plc5_address` and :mod:`~gateway.protocols.df1.plc5_commands` - PLC-5
  addresses and the requests built on them
* :mod:`~gateway.protocols.df1.write_verdict` - the exactly-once verdict of a write

The transition tables' type and checks are the protocols' shared :mod:`gateway.protocols.transitions`.
Nothing here does I/O; the caller passes ``now`` and moves the bytes.

Import from the modules themselves (``from gateway.protocols.df1.pccc import PcccError``): this
package re-exports nothing, so that each name has one home and one ``__all__``.
"""
