"""The fast-math flags every numba kernel of ctpipe compiles with.

``fastmath=True`` is LLVM's ``fast``, which includes ``nsz`` (signed zeros may be ignored).
With ``reassoc`` and ``nsz`` together, the code numba compiles in a process and the code it
loads from its on-disk cache (``cache=True``) are not the same: FDK volumes of one input differed
in their last bits, and the default pipeline's angles on a 48-view scan came out 6e-7 deg apart
between a Dask worker that loaded the kernels and a client that compiled them. Each flag alone,
and every flag but ``nsz``, gives bit-identical results either way, at the same speed (FDK
backprojection within 1 % of ``fastmath=True``). Hence ``fastmath=FASTMATH`` everywhere.
"""

from __future__ import annotations

__all__ = ["FASTMATH"]

#: LLVM's ``fast`` without ``nsz``: fused multiply-add, reassociation, reciprocals, approximate
#: functions, no NaN or infinity operands. A set, as numba requires (a frozenset is refused).
FASTMATH = {"contract", "reassoc", "arcp", "afn", "nnan", "ninf"}
