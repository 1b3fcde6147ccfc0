"""The shared test helpers of ``support/`` (synthetic logs, the PF-net stand-in world),
importable from every test folder, which mirror the package's subpackages."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent / "support"))
