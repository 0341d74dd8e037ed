"""Left only for the modules being restructured that still import it: use :mod:`svr.validation`.

:mod:`svr.models.brain_mask` and :mod:`svr.reconstruction.mask_fusion` import
``is_finite_number`` from here; delete this module once they import it from
:mod:`svr.validation`.
"""

from __future__ import annotations

from svr.validation import is_finite_number

__all__ = ["is_finite_number"]
