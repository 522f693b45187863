"""`python -m rigspace.train DATASET --out MODEL ...`: `rigspace train`, the form torchrun runs."""

from __future__ import annotations

import sys

from rigspace.sdk.cli import main

if __name__ == "__main__":
    sys.exit(main(["train", *sys.argv[1:]]))
