import os
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

# Compiled circuits go to a throwaway cache (shared by daemons the tests start), never to
# the user's cache, unless the caller chose one.
os.environ.setdefault("SNAIL_CACHE_DIR", tempfile.mkdtemp(prefix="snail-test-cache-"))
