#!/usr/bin/env python3
"""Regenerate the bundled synthetic samples (see stereocli/synth/samples.py for the layout).

    python samples/generate.py [OUTDIR]    # default: the folder of this script
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT.parent))  # run from a checkout without installing

from stereocli.synth.samples import generate_samples  # noqa: E402

if __name__ == "__main__":
    generate_samples(Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT)
