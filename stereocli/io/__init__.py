"""File formats: images, PFM, 16-bit PNG, Middlebury calib.txt, atomic writes, input pairing."""
