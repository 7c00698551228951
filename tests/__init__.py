"""skinpipe's tests. Imported before any test module or conftest: every cache skinpipe
keeps (OpenCL programs and PoCL's kernels, kept tables, the blur switch, seam layouts)
goes to a folder of the test run's own, made empty here and removed at exit, so that a
test run neither reads what an earlier version left in the user's cache nor writes
into it. Child processes the tests start inherit it."""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile

_CACHE = tempfile.mkdtemp(prefix="skinpipe-test-cache-")
atexit.register(shutil.rmtree, _CACHE, ignore_errors=True)
os.environ["XDG_CACHE_HOME"] = _CACHE
for _name in ("POCL_CACHE_DIR", "SKINPIPE_LAYOUT_CACHE"):
    os.environ.pop(_name, None)
