"""Progress bars for long work (tqdm on stderr; quiet when PHOTOREAL_QUIET=1)."""

from __future__ import annotations

import os

from tqdm.auto import tqdm


def progress_bar(total: int | None = None, desc: str = "", unit: str = "it", disable: bool = False):
    quiet = os.environ.get("PHOTOREAL_QUIET", "") not in ("", "0")
    return tqdm(total=total, desc=desc, unit=unit, disable=disable or quiet, dynamic_ncols=True, leave=False,
                mininterval=1.0)
