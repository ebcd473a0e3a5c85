"""Compare two evaluation.h5 files: every dataset bit for bit (``array_equal`` with ``equal_nan``
and ``signbit``), every plain attribute; else the largest relative difference (issue 25).

    python benchmarks/compare_evaluation_h5.py A/evaluation.h5 B/evaluation.h5

Object-reference attributes (HDF5 dimension scales) and the run's provenance are skipped.
"""

from __future__ import annotations

import sys

import h5py
import numpy as np

_SKIP = ("created", "command", "seconds", "timings", "provenance", "run_seconds", "DIMENSION_LIST", "REFERENCE_LIST")


def _attrs_equal(va, vb) -> bool:
    if isinstance(va, (str, bytes)) or isinstance(vb, (str, bytes)):
        return va == vb
    return np.array_equal(np.asarray(va), np.asarray(vb))


def main(path_a: str, path_b: str) -> int:
    a, b = h5py.File(path_a, "r"), h5py.File(path_b, "r")
    names, names_b = [], []
    a.visititems(lambda n, o: names.append(n))
    b.visititems(lambda n, o: names_b.append(n))
    if sorted(names) != sorted(names_b):
        print(f"different objects: {sorted(set(names) ^ set(names_b))}")
        return 1
    same = diff = 0
    for n in ["/", *names]:
        oa, ob = a[n], b[n]
        for k in oa.attrs:
            if k not in _SKIP and not _attrs_equal(oa.attrs[k], ob.attrs.get(k)):
                diff += 1
                print(f"ATTR {n}@{k}: {str(oa.attrs[k])[:200]} | {str(ob.attrs.get(k))[:200]}")
        if not isinstance(oa, h5py.Dataset):
            continue
        x, y = oa[()], ob[()]
        if x.dtype.kind in "fc":
            eq = x.shape == y.shape and np.array_equal(x, y, equal_nan=True) and \
                np.array_equal(np.signbit(np.real(x)), np.signbit(np.real(y)))
        else:
            eq = np.array_equal(x, y)
        if eq:
            same += 1
            continue
        diff += 1
        if x.dtype.kind == "f" and x.shape == y.shape:
            m = np.isfinite(x) & np.isfinite(y)
            rel = np.max(np.abs(x[m] - y[m]) / np.maximum(np.abs(y[m]), 1e-300)) if m.any() else np.nan
            print(f"DIFF {n} {x.dtype} {x.shape}: max rel {rel:.3e}, {np.count_nonzero(x != y)} elements differ")
        else:
            print(f"DIFF {n} {x.dtype} {x.shape}")
    print(f"{same} datasets bit-identical; {diff} datasets or attributes differ")
    return 1 if diff else 0


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    sys.exit(main(sys.argv[1], sys.argv[2]))
