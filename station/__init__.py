"""station: turntable capture-to-asset with Noise Guided Splatting."""

__version__ = "0.1.0"
