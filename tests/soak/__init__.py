"""Fault soak of both protocols through a fault-injecting proxy (quick by default, long with --soak)."""
