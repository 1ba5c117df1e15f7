"""Hypothesis strategies of the file cases (run worker-side by ``files_runner.py``): paths
with odd bytes, special files in place of inputs, concurrent writers (threads and processes)
to one path, outputs aliasing an input, writes under an address-space limit, and map files
crafted with a valid checksum (the checksum is FNV-1a over the header and tensors,
reimplemented in ``files_runner.checksum``, so its content is whatever the case chooses)."""

from __future__ import annotations

from typing import Any

from hypothesis import strategies as st

try:
    from .files_runner import ODD_NAMES
except ImportError:  # imported as a top-level module (benchmarks/adversarial.py)
    from files_runner import ODD_NAMES  # type: ignore[no-redef]

WRITERS = {"json": "json", "tum": "txt", "map": "geoloc"}
READERS = {"map": ("geoloc", "small_map_file"), "image": ("png", None), "pose": ("txt", None),
           "reference": ("txt", None), "onnx": ("onnx", None), "localize": ("png", None)}
#: What a header value is set to in a crafted map (checksummed, so only the content checks stand).
CRAFTED_VALUES = [None, -1, 0, 1e308, -1e308, 2**64, "x", "", [], {}, [1.0, 2.0], True, "<delete>", 1e-320]
HEADER_PATHS = [
    ["camera"], ["camera", "fx"], ["camera", "width"], ["keyframes"], ["keypoints"], ["descriptor_kind"],
    ["descriptor_width"], ["retrieval"], ["pose_covariances"], ["frontend"], ["frontend", "features"],
    ["frontend", "features", "kind"], ["frontend", "features", "n_features"], ["frontend", "camera", "width"],
    ["frontend", "camera", "dist"], ["frontend", "retrieval"], ["frontend", "version"], ["map_noise"],
    ["self_calibration"], ["labels"],
]
PATCHES = [b"\xff" * 8, b"\x00" * 64, b"\x00\x00\x00\x00\x00\x00\xf8\x7f" * 4, b"\x00\x00\x00\x00\x00\x00\xf0\x7f",
           b"\xff\xff\xff\xff\xff\xff\xff\x7f", b"\x01"]


def _case(files: dict[str, Any], names: list[str], timeout: float = 10, check: str = "any") -> dict[str, Any]:
    return {"module": "files", "files": files, "names": names, "timeout": timeout, "check": check}


@st.composite
def odd_path_cases(draw: st.DrawFn) -> dict[str, Any]:
    name = draw(st.sampled_from(sorted(ODD_NAMES)))
    in_folder = draw(st.booleans())
    if draw(st.booleans()):
        writer = draw(st.sampled_from(sorted(WRITERS)))
        return _case({"kind": "odd", "op": "write", "writer": writer, "suffix": WRITERS[writer], "name": name,
                      "in_folder": in_folder}, ["path"], timeout=60)
    reader = draw(st.sampled_from(["map", "image", "pose", "localize"]))
    suffix, source = READERS[reader]
    exists = source is not None and draw(st.booleans())
    return _case({"kind": "odd", "op": "read", "reader": reader, "suffix": suffix, "name": name, "in_folder": in_folder,
                  "exists": exists, "source": source}, ["path", "image"], timeout=60)


@st.composite
def special_cases(draw: st.DrawFn) -> dict[str, Any]:
    special = draw(st.sampled_from(["fifo", "fifo", "dir", "dangling"]))
    if draw(st.integers(0, 4)) == 0:
        return _case({"kind": "special", "op": "cli", "special": special, "suffix": "geoloc"}, ["--map"], timeout=60)
    reader = draw(st.sampled_from(sorted(READERS)))
    return _case({"kind": "special", "op": "read", "reader": reader, "special": special, "suffix": READERS[reader][0]},
                 ["path", "image", "reference file", "checkpoint"], timeout=10 if reader not in ("localize",) else 60)


@st.composite
def concurrent_cases(draw: st.DrawFn) -> dict[str, Any]:
    writer = draw(st.sampled_from(sorted(WRITERS)))
    how = draw(st.sampled_from(["threads", "processes"]))
    n = draw(st.integers(2, 6 if how == "threads" else 3))
    return _case({"kind": "concurrent", "writer": writer, "how": how, "n": n, "suffix": WRITERS[writer]}, ["path"],
                 timeout=120)


@st.composite
def alias_cases(draw: st.DrawFn) -> dict[str, Any]:
    alias = draw(st.sampled_from(["same", "dot", "symlink", "hardlink", "parent"]))
    return _case({"kind": "alias", "alias": alias}, ["--out"], timeout=90)


@st.composite
def limited_cases(draw: st.DrawFn) -> dict[str, Any]:
    writer = draw(st.sampled_from(sorted(WRITERS)))
    margin = draw(st.sampled_from([0, 1, 4, 16, 64]))
    return _case({"kind": "limited", "writer": writer, "margin_mb": margin, "suffix": WRITERS[writer]}, ["path"], timeout=60)


@st.composite
def crafted_cases(draw: st.DrawFn) -> dict[str, Any]:
    header_path = draw(st.one_of(st.none(), st.sampled_from(HEADER_PATHS)))
    value = draw(st.sampled_from(CRAFTED_VALUES))
    tensor = draw(st.one_of(st.none(), st.tuples(st.just(""), st.integers(0, 50), st.sampled_from(PATCHES))))
    if header_path is None and tensor is None:
        tensor = ("", 0, PATCHES[0])
    return _case({"kind": "crafted", "header_path": header_path, "value": value, "tensor": tensor}, ["path"], timeout=60)


def file_cases() -> st.SearchStrategy[dict[str, Any]]:
    """Every kind of file case."""
    return st.one_of(odd_path_cases(), special_cases(), concurrent_cases(), alias_cases(), limited_cases(), crafted_cases())
