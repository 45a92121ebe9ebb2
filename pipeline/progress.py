"""Progress bars: one helper so every stage shows progress the same way (tqdm on stderr)."""
from __future__ import annotations

import sys

from tqdm.auto import tqdm


def progress(total: int, desc: str, unit: str = "it", initial: int = 0, disable: bool = False) -> tqdm:
    # mininterval keeps CI logs short; dynamic_ncols keeps the bar readable in narrow terminals.
    return tqdm(total=total, initial=initial, desc=desc, unit=unit, disable=disable, file=sys.stderr,
                mininterval=1.0, dynamic_ncols=True)
