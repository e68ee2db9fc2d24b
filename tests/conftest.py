import os
import sys
import tempfile
from pathlib import Path

from hypothesis import settings

sys.path.insert(0, str(Path(__file__).parent))

# Compiled circuits go to a throwaway cache (shared by daemons the tests start), never to
# the user's cache, unless the caller chose one.
os.environ.setdefault("SNAIL_CACHE_DIR", tempfile.mkdtemp(prefix="snail-test-cache-"))

# CI decides whether work lands, so there the randomized tests draw the same examples on
# every run (a rare unlucky draw must not block a merge); developers' runs stay random and
# keep exploring. Failures found either way are pinned with @example.
settings.register_profile("ci", derandomize=True, database=None, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")
