"""Where the shared folder is: $SNAIL_SHARED, else ../shared beside the repository."""

import os
from pathlib import Path

SHARED = Path(os.environ.get("SNAIL_SHARED") or Path(__file__).resolve().parents[2] / "shared")
BRISTOL = SHARED / "circuits" / "bristol"
EXAMPLES = SHARED / "examples"
