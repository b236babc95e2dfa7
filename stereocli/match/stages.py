"""Imports every module that registers stages, so the registry is complete.

Add a line here when you add a stage module.
"""

from . import preprocess  # noqa: F401
from . import cost  # noqa: F401
from . import aggregate  # noqa: F401
from .optimize import wta  # noqa: F401
from . import refine  # noqa: F401
