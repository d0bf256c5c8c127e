"""Northbound Sparkplug B 3.0: the gateway as an edge node, each link a device (docs/guide/sparkplug.md)."""
