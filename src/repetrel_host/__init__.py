"""repetrel-host: streams G-code to Hyrel printers' motion controllers."""

__version__ = "0.1.0"
