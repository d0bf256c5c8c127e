"""DF1 full duplex (1770-6.5.16 chapter 4), sans-I/O: one station, in the role of a master or of a target.

What this package owns, and nothing else:

* :mod:`.station` - the full-duplex station, one transmitter and one receiver working at the same
  time, in either role; :mod:`.table` - its receiver table and its transmitter table, as data;
* :mod:`.datalink` - the station as the master's data link (DLE ACK / NAK / ENQ, the ACK timer);
* :mod:`.transaction` - PCCC transactions over that data link: TNS, reply matching, retries;
* :mod:`.responder` - the station as the target's responder (a PLC's MSG instruction addresses
  the gateway), with its events and counters in :mod:`.responder_events`.

What both duplex modes share stays one level up in :mod:`gateway.protocols.df1`: the framing and
its checks, PCCC, the addresses and the verdict of a write; the transition tables' form is every
core's, :mod:`gateway.protocols.transitions`.
Import from the modules themselves: this package re-exports nothing.
"""
