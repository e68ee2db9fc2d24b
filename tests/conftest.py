import atexit
import os
import shutil
import sys
import tempfile
from pathlib import Path

from hypothesis import settings

from snail_common import families

sys.path.insert(0, str(Path(__file__).parent))
families.register_all()  # every circuit id the tests name

# Compiled circuits go to a throwaway cache (shared by daemons the tests start), never to
# the user's cache, unless the caller chose one. It holds gigabytes once the large circuits
# are compiled, so it goes when the run ends.
if not os.environ.get("SNAIL_CACHE_DIR"):
    os.environ["SNAIL_CACHE_DIR"] = tempfile.mkdtemp(prefix="snail-test-cache-")
    atexit.register(shutil.rmtree, os.environ["SNAIL_CACHE_DIR"], ignore_errors=True)
# The native kernel is compiled once per run into a folder every daemon of the run shares
# (each fixture's fresh circuit cache would compile it again).
if not os.environ.get("SNAIL_KERNEL_DIR"):
    os.environ["SNAIL_KERNEL_DIR"] = os.path.join(os.environ["SNAIL_CACHE_DIR"],
                                                  "native-kernel")

# CI decides whether work lands, so there the randomized tests draw the same examples on
# every run (a rare unlucky draw must not block a merge); developers' runs stay random and
# keep exploring. Failures found either way are pinned with @example.
settings.register_profile("ci", derandomize=True, database=None, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")
