"""Parent side of the adversarial worker (see ``worker.py``): send one case, wait with a
timeout, classify. A dead worker (signal, abort) or a timed-out one is replaced by a fresh
process; the case that killed it is the one in flight, so no bisection is needed."""

from __future__ import annotations

import os
import pickle
import select
import signal
import struct
import subprocess
import sys
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
#: Seconds one case may take unless it says otherwise (the promise is "a few seconds"; a case
#: that blocks — on a FIFO, say — is a hang after this long).
DEFAULT_TIMEOUT_S = float(os.environ.get("GEOLOC_ADV_TIMEOUT", "10"))
GOOD = ("ok", "rejected")


class Worker:
    def __init__(self) -> None:
        self.proc: subprocess.Popen[bytes] | None = None
        self.restarts = 0

    def _start(self) -> subprocess.Popen[bytes]:
        env = dict(os.environ)
        env.setdefault("GEOLOC_NUM_THREADS", "1")
        env["PYTHONPATH"] = os.pathsep.join([str(HERE), env.get("PYTHONPATH", "")])
        env.setdefault("MPLBACKEND", "Agg")
        proc = subprocess.Popen(
            [sys.executable, str(HERE / "worker.py")],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env,
        )
        assert proc.stdout is not None
        ready = self._read(proc, 4, 120.0)
        if ready != b"RDY!":
            raise RuntimeError("adversarial worker failed to start")
        return proc

    @staticmethod
    def _read(proc: subprocess.Popen[bytes], n: int, timeout: float) -> bytes | None:
        assert proc.stdout is not None
        fd = proc.stdout.fileno()
        buf = b""
        while len(buf) < n:
            r, _, _ = select.select([fd], [], [], timeout)
            if not r:
                return None
            chunk = os.read(fd, n - len(buf))
            if not chunk:
                return b""
            buf += chunk
        return buf

    def _kill(self) -> int | None:
        if self.proc is None:
            return None
        self.proc.kill()
        code = self.proc.wait()
        self._release()
        return code

    def _release(self) -> None:
        if self.proc is not None:
            for f in (self.proc.stdin, self.proc.stdout):
                if f is not None:
                    try:
                        f.close()
                    except OSError:
                        pass
        self.proc = None

    def close(self) -> None:
        if self.proc is not None:
            assert self.proc.stdin is not None
            self.proc.stdin.close()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self._kill()
            self._release()

    def run(self, case: dict[str, Any], timeout: float | None = None) -> dict[str, Any]:
        timeout = timeout or case.get("timeout") or DEFAULT_TIMEOUT_S
        if self.proc is None or self.proc.poll() is not None:
            self.proc = self._start()
        assert self.proc.stdin is not None
        data = pickle.dumps(case)
        try:
            self.proc.stdin.write(struct.pack(">I", len(data)) + data)
            self.proc.stdin.flush()
        except BrokenPipeError:
            self._kill()
            self.restarts += 1
            return {"kind": "crash", "detail": "worker gone before the case"}
        head = self._read(self.proc, 4, timeout)
        if head is None:
            self._kill()
            self.restarts += 1
            return {"kind": "hang", "detail": f"no answer in {timeout:.0f} s"}
        if len(head) < 4:
            code = self.proc.wait()
            self._release()
            self.restarts += 1
            sig = -code if code < 0 else None
            name = signal.Signals(sig).name if sig else f"exit {code}"
            return {"kind": "crash", "detail": f"worker died: {name}"}
        body = self._read(self.proc, struct.unpack(">I", head)[0], 60.0)
        assert body
        out: dict[str, Any] = pickle.loads(body)
        return out


def describe(case: dict[str, Any]) -> str:
    """A short, reproducible rendering of a case's expression (for failure messages)."""

    def r(e: Any) -> str:
        import numpy as np

        if isinstance(e, tuple) and e and isinstance(e[0], str):
            if e[0] == "call":
                t = e[1] if isinstance(e[1], str) else r(e[1])
                a = [r(x) for x in e[2]] + [f"{k}={r(v)}" for k, v in e[3].items()]
                return f"{t}({', '.join(a)})"
            if e[0] == "attr":
                return f"{r(e[1])}.{e[2]}"
            if e[0] == "cached":
                return f"<{e[1]}>"
            if e[0] == "file":
                return f"<file {e[1][:24]!r}…{e[2]}>"
            if e[0] == "path":
                return f"<{e[1]} path>"
            if e[0] in ("tuple", "list"):
                return "[" + ", ".join(r(x) for x in e[1]) + "]"
            if e[0] == "lit":
                return repr(e[1])
        if isinstance(e, np.ndarray):
            flags = "" if e.flags.c_contiguous else " noncontig"
            flags += "" if e.flags.writeable else " readonly"
            head = np.array2string(e.ravel()[:4], precision=3) if e.dtype != object else "…"
            return f"array{e.shape}:{e.dtype}{flags} {head}"
        s = repr(e)
        return s if len(s) < 80 else s[:77] + "..."

    if case.get("files") is not None:
        return "files " + ", ".join(f"{k}={v!r:.60}" for k, v in case["files"].items())
    if case.get("cli") is not None:
        return "geoloc " + " ".join(map(str, (r(a) for a in case["cli"])))
    return r(case["expr"])


class Tally:
    """Counts per module: cases, passed, failures by kind (for the long profile's report)."""

    def __init__(self) -> None:
        self.counts: dict[str, Counter[str]] = defaultdict(Counter)
        self.examples: dict[tuple[str, str], list[str]] = defaultdict(list)

    def add(self, module: str, case: dict[str, Any], out: dict[str, Any]) -> None:
        c = self.counts[module]
        c["cases"] += 1
        if out["kind"] in GOOD:
            c["passed"] += 1
            c[out["kind"]] += 1
        else:
            c["fail:" + out["kind"]] += 1
            ex = self.examples[(module, out["kind"])]
            if len(ex) < 5:
                ex.append(f"{describe(case)}\n      -> {out['detail']}")
