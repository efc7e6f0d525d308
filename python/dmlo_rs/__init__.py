"""dmlo_rs — the Rust geometry core of DMLO, with numpy in and out.

Every function releases the GIL while it works and raises ``ValueError`` / ``TypeError`` naming the
argument at fault on bad input.
"""

from dmlo_rs import _dmlo_rs
from dmlo_rs._dmlo_rs import *  # noqa: F403 -- the compiled module is the API; its __all__ lists it

__all__ = list(_dmlo_rs.__all__)
