"""Registers and spills of the Warp list-free LJ walks on a CUDA
architecture, without a GPU: each walk's module compiled ahead of time to
PTX by Warp (NVRTC), then assembled by ``ptxas -v``. The thread walk
(`jaxrt.backends.cell.warp_kernels.walk_kernel`), the cluster walk
(`jaxrt.backends.cell.warp_cluster.cluster_kernel`, loops over the
cluster unrolled as on CUDA) and the warp-cooperative walk
(`jaxrt.backends.cell.warp_cluster_native.native_kernel`), per cluster
size, with the MD step's flags (``md``: forces and energy) and with every
output (``all``: count, derivatives, radii).

Where NVRTC writes a newer PTX ISA than ``ptxas`` reads, the PTX's
``.version`` line is lowered to ``ptxas``' (the walks use no newer
instruction; ``ptxas`` refuses the file otherwise).

    python benchmarks/warp_registers.py --arch 90 --out /tmp/registers.csv
"""
from __future__ import annotations

import argparse
import csv
import os
import re
import subprocess
import sys
import tempfile


def assemble(ptx: str, arch: int) -> dict:
    """``ptxas -v`` of the file ``ptx``: registers, stack and spills."""
    data = open(ptx, "rb").read().replace(b"\0", b"")
    for _ in range(2):
        with open(ptx, "wb") as f:
            f.write(data)
        r = subprocess.run(["ptxas", f"-arch=sm_{arch}", "-v", ptx, "-o",
                            os.devnull], capture_output=True, text=True)
        m = re.search(r"current version is '([\d.]+)'", r.stderr)
        if r.returncode == 0 or not m:
            break
        data = re.sub(rb"^\.version [\d.]+", b".version " + m[1].encode(),
                      data, flags=re.M)
    if r.returncode:
        return {"error": r.stderr.strip().splitlines()[-1]}
    text = r.stderr
    number = lambda pattern: int(re.findall(pattern, text)[-1])  # noqa: E731
    return {"registers": number(r"Used (\d+) registers"),
            "stack_bytes": number(r"(\d+) bytes stack frame"),
            "spill_stores": number(r"(\d+) bytes spill stores"),
            "spill_loads": number(r"(\d+) bytes spill loads")}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--arch", type=int, default=90)
    parser.add_argument("--sizes", type=int, nargs="+", default=[4, 8, 16])
    parser.add_argument("--out", default=None, help="CSV path")
    args = parser.parse_args(argv)
    import warp as wp
    wp.config.quiet = True
    from jaxrt.backends.cell import warp_cluster as wc
    from jaxrt.backends.cell import warp_cluster_native as wcn
    from jaxrt.backends.cell import warp_kernels as wk
    periodic = 7 * wk.PERIODIC
    flag_sets = {"md": periodic, "all": periodic | wk.COUNT | wk.DERIVATIVES
                 | wk.HAS_RADII}
    walks = []
    for tag, flags in flag_sets.items():
        for scalar, name in ((wp.float32, "float32"), (wp.float64, "float64")):
            walks.append(("thread", 1, tag, name,
                          wk.walk_kernel(scalar, flags)))
            for size in args.sizes:
                walks.append(("cluster", size, tag, name, wc.cluster_kernel(
                    scalar, flags, size=size, unroll=True)))
                if size in wcn.SIZES:
                    walks.append(("native", size, tag, name,
                                  wcn.native_kernel(scalar, flags,
                                                    size=size)))
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for n, (walk, size, tag, name, kernel) in enumerate(walks):
            paths = wp.compile_aot_module(
                kernel.module, arch=args.arch, use_ptx=True,
                module_dir=os.path.join(folder, str(n)))
            row = {"walk": walk, "size": size, "flags": tag, "dtype": name,
                   "arch": f"sm_{args.arch}",
                   **assemble(str(paths[0]), args.arch)}
            rows.append(row)
            print("  ".join(f"{k}={v}" for k, v in row.items()), flush=True)
    if args.out:
        keys = list(dict.fromkeys(k for row in rows for k in row))
        with open(args.out, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=keys)
            writer.writeheader()
            writer.writerows(rows)
        print(f"wrote {args.out}")


if __name__ == "__main__":
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(
        __file__))))
    main()
