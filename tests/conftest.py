import sys
from pathlib import Path

# Make this checkout's packages (and tests/helpers.py) importable whatever is installed.
_REPO = Path(__file__).resolve().parents[1]
for p in (str(_REPO), str(_REPO / "tests")):
    if p not in sys.path:
        sys.path.insert(0, p)
