"""The one error type of the bag layer and the hint every damaged-file message ends with."""

from __future__ import annotations

MCAP_MAGIC = b"\x89MCAP0\r\n"
REPAIR_HINT = "run `lenn-ros bag-repair {path}` to rebuild it from its complete chunks"


class BagError(ValueError):
    """A bag that cannot be used, with a message that names the problem and the fix."""
