"""stereocli: stereo vision on image folders (calibrate, rectify, match, triangulate, eval).

Conventions used everywhere in the package:

* Images are ``numpy.ndarray`` of shape ``(H, W)`` or ``(H, W, 3)`` (RGB order), float32 in
  [0, 255] inside the matching pipeline.
* Disparity is ``(H, W)`` float32 in pixels, referenced to the left image,
  ``x_right = x_left - d``; invalid / unknown pixels are ``+inf`` (never a sentinel).
* Cost volumes are ``(H, W, D)`` C-contiguous float32, ``D = ndisp``, index ``k`` is disparity
  ``min_disp + k``, lower is better; entries whose right pixel falls outside the image hold the
  cost stage's maximum cost.
"""

__version__ = "0.1.0"
