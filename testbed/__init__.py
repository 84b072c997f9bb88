"""Real-time testbed for linearization-based quantized control under DoS attacks."""

__version__ = "0.1.0"
