"""The dtype of SDR index arrays: the models compute with it, the store decodes its blobs to it."""

from __future__ import annotations

import numpy as np

__all__ = ["INDEX_DTYPE"]

#: Sorted active-bit indices of an SDR (codes, winner cells) as arrays.
INDEX_DTYPE = np.int32
