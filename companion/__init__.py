"""companion: onboard search-and-track of ground targets with a GM-PHD filter (Sung & Tokekar)."""

__version__ = "0.1.0"
