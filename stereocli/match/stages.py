"""Imports every module that registers stages, so the registry is complete.

Add a line here when you add a stage module.
"""

from . import preprocess  # noqa: F401
from . import cost  # noqa: F401
from . import cost_mi  # noqa: F401
from . import aggregate  # noqa: F401
from .optimize import wta  # noqa: F401
from .optimize import sgm  # noqa: F401
from . import refine  # noqa: F401
from .optimize import dp, so, bp, gc, coop  # noqa: F401,E401
from . import refine_segment  # noqa: F401
from . import refine_local  # noqa: F401
from . import refine_voting  # noqa: F401
