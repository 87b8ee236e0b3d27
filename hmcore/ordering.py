"""How hmflow orders names for people: wells, layers and regions in the order an engineer
expects."""

from __future__ import annotations

import re


def natural_key(name: object) -> tuple:
    """Sort key of a name with numbers in it: digit runs compare as numbers, so that PRO-4
    comes before PRO-11 and PROD2 before PROD10."""
    return tuple(int(t) if t.isdigit() else t for t in re.split(r"(\d+)", str(name)))
