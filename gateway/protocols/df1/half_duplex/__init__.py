"""DF1 half duplex (1770-6.5.16 chapter 3), sans-I/O: the master of a multi-drop line.

What this package owns, and nothing else:

* :mod:`.master` - the line master core: polls, master messages, resends, its transition table;
* :mod:`.events` - its configuration (line, stations) and the events it reports;
* :mod:`.schedule` - the stations of the line and the choice of the next exchange;
* :mod:`.transmitter` - when bytes may go (quiet time, RTS keying) and echo suppression;
* :mod:`.transactions` - PCCC transactions over the master: TNS, retries, a write's verdict;
* :mod:`.slave_messages` - the reply to a message a slave initiates (MSG, report by exception).

What both duplex modes share stays one level up in :mod:`gateway.protocols.df1`: the framing and
its checks, PCCC, the addresses and the verdict of a write; the transition tables' form is every
core's, :mod:`gateway.protocols.transitions`.
Import from the modules themselves: this package re-exports nothing.
"""
