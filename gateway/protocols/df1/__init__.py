"""Sans-I/O DF1 full duplex and PCCC for SLC 500 and PLC-5 controllers.

* :mod:`~gateway.protocols.df1.framing` - DLE framing of both duplex modes; its streaming decoder is
  :mod:`~gateway.protocols.df1.framing.decoder`, the checks (BCC / CRC-16) :mod:`~gateway.protocols.df1.checks`
* :mod:`~gateway.protocols.df1.datalink` - the full-duplex data-link layer (ACK / NAK / ENQ, timers)
* :mod:`~gateway.protocols.df1.responder` - the full-duplex responder (DF1 target mode: commands in, replies out)
* :mod:`~gateway.protocols.df1.pccc` - PCCC command / reply packets, STS codes, size limits, TNS
* :mod:`~gateway.protocols.df1.address` - SLC 500 logical addresses (``N7:0``, ``T4:3.ACC`` ...)

Nothing here does I/O; the caller passes ``now`` and moves the bytes.

Import from the modules themselves (``from gateway.protocols.df1.pccc import PcccError``): this
package re-exports nothing, so that each name has one home and one ``__all__``.
"""
