"""dmlo_rs — the Rust geometry core of DMLO, with numpy in and out.

Every function releases the GIL while it works and raises ``ValueError`` / ``TypeError`` naming the
argument at fault on bad input. Valid input whose data admit no solution (too few pairs or map
correspondences, degenerate points) raises ``RegistrationError``, a ``ValueError`` subclass to fall back on.
"""

from dmlo_rs._instruction_set import check_instruction_set

check_instruction_set()

from dmlo_rs import _dmlo_rs  # noqa: E402 -- only once the processor is known to run it
from dmlo_rs._dmlo_rs import *  # noqa: E402, F403 -- the compiled module is the API; its __all__ lists it

__all__ = list(_dmlo_rs.__all__)
