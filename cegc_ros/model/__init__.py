"""The CEGC network (one module per paper section) and its losses."""

from .cegc import CEGC, CEGCOutput
from .config import ModelConfig

__all__ = ["CEGC", "CEGCOutput", "ModelConfig"]
