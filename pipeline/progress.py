"""Progress bars: one helper so every stage shows progress the same way (tqdm on stderr)."""
from __future__ import annotations

import sys
from typing import Iterable

from tqdm.auto import tqdm


def progress(iterable: Iterable | None = None, *, total: int | None = None, desc: str, unit: str = "it",
             initial: int = 0, disable: bool = False, leave: bool = True) -> tqdm:
    # mininterval keeps CI logs short; dynamic_ncols keeps the bar readable in narrow terminals.
    return tqdm(iterable, total=total, initial=initial, desc=desc, unit=unit, disable=disable, leave=leave,
                file=sys.stderr, mininterval=1.0, dynamic_ncols=True)
