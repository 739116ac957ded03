"""Map re-use: relocalisation after a loss of visual tracking and guided re-finding of map points."""

from runtime.reloc.relocalizer import Relocalization, Relocalizer, RelocConfig

__all__ = ["RelocConfig", "Relocalization", "Relocalizer"]
