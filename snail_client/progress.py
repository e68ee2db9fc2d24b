"""Progress bars for work a person waits on: on a terminal only, never with -q."""

from __future__ import annotations

import sys

from tqdm import tqdm


def bar(total: int, desc: str, quiet: bool = False, unit: str = "it") -> tqdm:
    """A bar on stderr, shown only when stderr is a terminal and not asked to be quiet
    (pipes and logs get no control characters)."""
    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, leave=False,
                disable=quiet or not sys.stderr.isatty(), dynamic_ncols=True)
