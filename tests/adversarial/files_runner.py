"""Worker-side runner of the file cases (``file_cases.py``): odd paths, special files,
concurrent writers, outputs aliasing inputs, memory limits and crafted-but-checksummed map
files. Each returns the worker's outcome dict; the invariants are: no crash, no hang (the
parent's timeout), no lost or half-written file (the target loads and is one complete
version; no temp file left), and an error names the argument."""

from __future__ import annotations

import json
import os
import resource
import shutil
import struct
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any, Callable

import numpy as np

#: Odd file-name parts: bytes that are not UTF-8, spaces, a newline, a leading '-', long names.
ODD_NAMES = {
    "surrogate": os.fsdecode(b"\xff\xfe"),
    "space": "a b  c",
    "newline": "a\nb",
    "dash": "-x",
    "long": "n" * 240,
    "toolong": "n" * 300,
    "dots": "..x",
}
_SEQ = 0


def _fresh_dir(tmp: Path) -> Path:
    global _SEQ
    _SEQ += 1
    d = tmp / f"files-{os.getpid()}-{_SEQ}"
    d.mkdir()
    return d


def _temps_left(folder: Path) -> list[str]:
    return [n for n in os.listdir(os.fsencode(folder)) if n.endswith(b".tmp")]  # type: ignore[misc]


# ------------------------------------------------------------------ writers and readers


def _writers(cache: Callable[[str], Any]) -> dict[str, tuple[Callable[[Path, int], None], Callable[[Path], Any]]]:
    """name → (write version k to path, read path back as a comparable value)."""
    import geoloc
    from geoloc._io import write_json_atomic

    def json_write(p: Path, k: int) -> None:
        write_json_atomic(p, {"version": k, "values": list(range(k * 1000, k * 1000 + 300))})

    def tum_write(p: Path, k: int) -> None:
        poses = np.repeat(np.eye(4)[None], 3, axis=0)
        poses[:, 0, 3] = k
        geoloc.evaluation.write_tum_trajectory(p, [0.0, 1.0, 2.0], poses)

    def map_write(p: Path, k: int) -> None:
        cache("small_map").save(p)

    return {
        "json": (json_write, lambda p: json.loads(Path(p).read_text())["version"]),
        "tum": (tum_write, lambda p: int(geoloc.datasets.tum.read_tum_trajectory(p)[1][0, 0, 3])),
        "map": (map_write, lambda p: len(geoloc.Map.load(p))),
    }


def _readers() -> dict[str, Callable[[Path], Any]]:
    import geoloc
    import geoloc.reference

    return {
        "map": geoloc.Map.load,
        "image": lambda p: geoloc.datasets.sequence.load_image(p, geoloc.Camera(525, 525, 320, 240)),
        "pose": geoloc.datasets.sevenscenes.read_7scenes_pose,
        "reference": geoloc.reference.load_reference,
        "onnx": geoloc.OnnxDescriptor,
        "localize": lambda p: geoloc.Localizer(_CACHE_FN("small_map")).localize(str(p), 0.0),
    }


_CACHE_FN: Callable[[str], Any] = lambda key: None  # noqa: E731 - set by run()


# ------------------------------------------------------------------ case kinds


def _odd_path(case: dict[str, Any], tmp: Path, cache: Callable[[str], Any]) -> dict[str, Any]:
    folder = _fresh_dir(tmp)
    part = ODD_NAMES[case["name"]]
    where = folder / part if case["in_folder"] else folder
    if case["in_folder"]:
        try:
            where.mkdir()
        except OSError:
            where = folder
    target = where / f"{part}.{case['suffix']}"
    if case["op"] == "write":
        write, read = _writers(cache)[case["writer"]]
        write(target, 1)
        return {"check_file": (str(target), read(target) is not None)}
    reader = _readers()[case["reader"]]
    if case["exists"]:
        try:
            shutil.copyfile(cache(case["source"]), target)
        except OSError:
            pass  # a name the file system cannot hold (too long): the reader sees no file
    return {"result": reader(target)}


def _special(case: dict[str, Any], tmp: Path, cache: Callable[[str], Any]) -> dict[str, Any]:
    folder = _fresh_dir(tmp)
    target = folder / f"in.{case['suffix']}"
    if case["special"] == "fifo":
        os.mkfifo(target)
    elif case["special"] == "dir":
        target.mkdir()
    else:
        os.symlink(folder / "nowhere", target)
    if case["op"] == "read":
        return {"result": _readers()[case["reader"]](target)}
    return {"cli": ["localize", "--map", str(target), "--format", "synthetic", "--synthetic-frames", "20",
                    "--frames", "0:2", "--out", str(folder / "p.txt")]}


def _concurrent(case: dict[str, Any], tmp: Path, cache: Callable[[str], Any]) -> dict[str, Any]:
    folder = _fresh_dir(tmp)
    target = folder / f"shared.{case['suffix']}"
    write, read = _writers(cache)[case["writer"]]
    n = case["n"]
    errors: list[str] = []
    if case["how"] == "threads":
        barrier = threading.Barrier(n)

        def run(k: int) -> None:
            barrier.wait()
            try:
                write(target, k)
            except Exception as e:  # noqa: BLE001 - every writer must succeed
                errors.append(f"{type(e).__name__}: {e}")

        threads = [threading.Thread(target=run, args=(k,)) for k in range(n)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    else:
        code = ("import sys, json\nsys.path.insert(0, sys.argv[3])\nimport files_runner, fixtures\n"
                "files_runner.write_version(sys.argv[1], sys.argv[2], int(sys.argv[4]))\n")
        procs = [subprocess.Popen([sys.executable, "-c", code, case["writer"], str(target), str(Path(__file__).parent), str(k)],
                                  stderr=subprocess.PIPE) for k in range(n)]
        for p in procs:
            _, err = p.communicate(timeout=60)
            if p.returncode:
                errors.append(err.decode(errors="replace")[-200:])
    if errors:
        return {"problem": f"{len(errors)} of {n} concurrent {case['writer']} writers failed: {errors[0][:200]}"}
    value = read(target)
    valid = {"map": [len(cache("small_map"))]}.get(case["writer"], list(range(n)))
    if value not in valid:
        return {"problem": f"the file holds {value!r}, not one complete version"}
    if _temps_left(folder):
        return {"problem": f"temp files left: {_temps_left(folder)}"}
    return {}


def write_version(writer: str, path: str, k: int) -> None:
    """One process's write (the ``processes`` kind of concurrent case)."""
    import fixtures

    cache: dict[str, Any] = {}
    tmp = Path(path).parent

    def get(key: str) -> Any:
        if key not in cache:
            cache[key] = getattr(fixtures, key)(tmp)
        return cache[key]

    _writers(get)[writer][0](Path(path), k)


def _alias(case: dict[str, Any], tmp: Path, cache: Callable[[str], Any]) -> dict[str, Any]:
    folder = _fresh_dir(tmp)
    the_map = folder / "m.geoloc"
    shutil.copyfile(cache("small_map_file"), the_map)
    out = {"same": str(the_map), "dot": str(folder / "." / "m.geoloc"), "symlink": str(folder / "l.geoloc"),
           "hardlink": str(folder / "h.geoloc"), "parent": str(folder / ".." / folder.name / "m.geoloc")}[case["alias"]]
    if case["alias"] == "symlink":
        os.symlink(the_map, out)
    elif case["alias"] == "hardlink":
        os.link(the_map, out)
    option = "--out"
    return {"cli": ["localize", "--map", str(the_map), "--format", "synthetic", "--synthetic-frames", "20",
                    "--frames", "0:2", option, out], "unchanged": (str(the_map), the_map.read_bytes()),
            "must_fail": True}


def _vm_size() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmSize:"):
            return int(line.split()[1]) * 1024
    return 0


def _limited(case: dict[str, Any], tmp: Path, cache: Callable[[str], Any]) -> dict[str, Any]:
    folder = _fresh_dir(tmp)
    target = folder / f"out.{case['suffix']}"
    write, read = _writers(cache)[case["writer"]]
    write(target, 0)  # the previous version, written without a limit
    cache("small_map")
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    limit = _vm_size() + case["margin_mb"] * 2**20
    outcome: dict[str, Any] = {}
    resource.setrlimit(resource.RLIMIT_AS, (limit if hard == resource.RLIM_INFINITY else min(limit, hard), hard))
    try:
        write(target, 1)
    except MemoryError:
        outcome["limited"] = True
    except Exception as e:  # noqa: BLE001 - a clean geoloc error is fine, classified below
        outcome["error"] = e
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))
    value = read(target)
    valid = {"map": [len(cache("small_map"))]}.get(case["writer"], [0, 1])
    if value not in valid:
        outcome["problem"] = f"after a write under RLIMIT_AS the file holds {value!r}"
    elif _temps_left(folder):
        outcome["problem"] = f"temp files left under RLIMIT_AS: {_temps_left(folder)}"
    return outcome


# ------------------------------------------------------------------ crafted map files


def fnv1a64_field(h: int, data: bytes, prefix: bool = True) -> int:
    """geoloc-core's FNV-1a 64 (``checksum.rs``), fed a length-prefixed field."""
    prime, mask = 0x100000001B3, 0xFFFFFFFFFFFFFFFF
    for b in (struct.pack("<Q", len(data)) if prefix else b"") + data:
        h = ((h ^ b) * prime) & mask
    return h


def checksum(header: str, tensors: dict[str, tuple[str, list[int], bytes]]) -> str:
    """The map file's checksum (``map/file.rs``): the header text, then per tensor in name
    order its name, dtype, shape and bytes."""
    h = fnv1a64_field(0xCBF29CE484222325, header.encode())
    for name in sorted(tensors):
        dtype, shape, data = tensors[name]
        h = fnv1a64_field(h, name.encode())
        h = fnv1a64_field(h, dtype.encode())
        for d in shape:
            h = fnv1a64_field(h, struct.pack("<Q", d), prefix=False)
        h = fnv1a64_field(h, data)
    return f"fnv1a64:{h:016x}"


def craft(source: bytes, edit_header: Callable[[dict[str, Any]], None] | None, edit_tensor: tuple[str, int, bytes] | None) -> bytes:
    """``source`` (a map file) with its JSON header and/or a tensor's bytes edited, the
    checksum recomputed: a file the format check accepts, with content chosen by the case."""
    n = struct.unpack("<Q", source[:8])[0]
    outer = json.loads(source[8 : 8 + n])
    data = bytearray(source[8 + n :])
    envelope = json.loads(outer["__metadata__"]["geoloc"])
    header = json.loads(envelope["header"])
    if edit_header is not None:
        edit_header(header)
    if edit_tensor is not None:
        names = sorted(k for k in outer if k != "__metadata__")
        name = names[edit_tensor[1] % len(names)] if edit_tensor[0] == "" else edit_tensor[0]
        start, end = outer[name]["data_offsets"]
        if end > start:
            patch = edit_tensor[2][: end - start]
            data[start : start + len(patch)] = patch
    tensors = {k: (v["dtype"], v["shape"], bytes(data[v["data_offsets"][0] : v["data_offsets"][1]]))
               for k, v in outer.items() if k != "__metadata__"}
    envelope["header"] = json.dumps(header, separators=(",", ":"))
    envelope["checksum"] = checksum(envelope["header"], tensors)
    outer["__metadata__"]["geoloc"] = json.dumps(envelope, separators=(",", ":"))
    head = json.dumps(outer, separators=(",", ":")).encode()
    head += b" " * (-len(head) % 8)
    return struct.pack("<Q", len(head)) + head + bytes(data)


def _set_path(header: dict[str, Any], path: list[Any], value: Any) -> None:
    node: Any = header
    for key in path[:-1]:
        if isinstance(node, dict) and key in node:
            node = node[key]
        elif isinstance(node, list) and isinstance(key, int) and node:
            node = node[key % len(node)]
        else:
            return
    last = path[-1]
    if isinstance(node, dict):
        if value == "<delete>":
            node.pop(last, None)
        else:
            node[last] = value
    elif isinstance(node, list) and node and isinstance(last, int):
        node[last % len(node)] = None if value == "<delete>" else value


def _crafted(case: dict[str, Any], tmp: Path, cache: Callable[[str], Any]) -> dict[str, Any]:
    import geoloc

    source = Path(cache("small_map_file")).read_bytes()
    folder = _fresh_dir(tmp)
    target = folder / "crafted.geoloc"
    edit = None if case["header_path"] is None else (lambda h: _set_path(h, case["header_path"], case["value"]))
    target.write_bytes(craft(source, edit, case["tensor"]))
    loaded = geoloc.Map.load(target)
    return {"result": loaded}


KINDS = {"odd": _odd_path, "special": _special, "concurrent": _concurrent, "alias": _alias, "limited": _limited,
         "crafted": _crafted}


def run(case: dict[str, Any], tmp: Path, cache: Callable[[str], Any]) -> dict[str, Any]:
    """Run ``case["files"]`` (its kind's parameters); what the worker classifies."""
    global _CACHE_FN
    _CACHE_FN = cache
    return KINDS[case["files"]["kind"]](case["files"], tmp, cache)
