import os
import sys
from pathlib import Path

# The CLI tests call jaxskel's main() in the test process, which turns JAX's persistent
# compilation cache on for the rest of that process (in ~/.cache/jaxskel/jax unless
# JAXSKEL_CACHE_DIR says otherwise). Tests should neither read programs cached by other
# code versions nor fill the developer's cache; the cache itself is tested in subprocesses
# with their own directory (test_fit_cli.py). Set JAXSKEL_CACHE_DIR to test with a cache.
os.environ.setdefault("JAXSKEL_CACHE_DIR", "")

import matplotlib

matplotlib.use("Agg")
sys.path.insert(0, str(Path(__file__).parent))
