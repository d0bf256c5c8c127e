"""slc-gateway: Modbus TCP gateway for Allen-Bradley SLC controllers."""

__all__ = ["__version__"]

__version__ = "0.1.0"
