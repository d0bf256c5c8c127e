"""The DF1 kind's simulators: SLC 5/04 and PLC-5 on full duplex, and a half-duplex multi-drop line."""
