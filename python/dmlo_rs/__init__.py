"""dmlo_rs — the Rust geometry core of DMLO, with numpy in and out.

Every function releases the GIL while it works and raises ``ValueError`` / ``TypeError`` naming the
argument at fault on bad input.
"""

from dmlo_rs._dmlo_rs import __version__

__all__ = ["__version__"]
