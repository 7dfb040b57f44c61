"""What wait policy an OpenMP runtime (libgomp) was loaded with, read from its own printout.

With ``OMP_DISPLAY_ENV=VERBOSE`` every OpenMP runtime prints the settings it loaded with,
at the moment it is loaded.  :func:`libgomp_settings` runs a probe script in a fresh
interpreter and reads the blocks printed between two marker lines the probe writes to
stderr; libgomp's blocks are told apart from other runtimes' (MKL's libiomp5, an OpenMP
OpenBLAS) by ``GOMP_SPINCOUNT``, which only libgomp prints.  The spin count is what tells
the policy apart: 0 for a runtime that waits passively, 300000 (or more) for one that spins.
"""

from __future__ import annotations

import os
import subprocess
import sys

BEGIN, END = "<<probe: begin>>", "<<probe: end>>"
PRINT_BEGIN = f"print({BEGIN!r}, file=sys.stderr, flush=True)"
PRINT_END = f"print({END!r}, file=sys.stderr, flush=True)"


def libgomp_settings(probe: str, **env_extra):
    """Run ``probe`` (which prints :data:`BEGIN` and :data:`END` to stderr around the load
    under test, and may print a last line of its own) with no OpenMP variable in the
    environment but ``env_extra``.  Returns ``([(spin count, wait policy)] of each libgomp
    block printed between the markers, stderr lines)``."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "OMP_NUM_THREADS")}
    env.update(OMP_DISPLAY_ENV="VERBOSE", **env_extra)
    p = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True,
                       text=True, check=True)
    lines = p.stderr.splitlines()
    during = lines[lines.index(BEGIN) + 1:lines.index(END)]
    blocks, block = [], None
    for ln in during:
        if "DISPLAY ENVIRONMENT BEGIN" in ln:
            block = {}
        elif "DISPLAY ENVIRONMENT END" in ln:
            blocks.append(block)
            block = None
        elif block is not None and "=" in ln:
            key, val = ln.split("=", 1)
            block[key.strip()] = val.strip(" '")
    return [(b["GOMP_SPINCOUNT"], b.get("OMP_WAIT_POLICY")) for b in blocks
            if "GOMP_SPINCOUNT" in b], lines
