"""The OPC UA server ([opcua]): the same images and write path as Modbus and Sparkplug (docs/guide/opcua.md)."""
