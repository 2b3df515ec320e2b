#!/usr/bin/env bash
# Test-only wheels that the staged GPU machine lacks (../shared/gpu/stage.sh
# brings Warp and jax-md): ASE, which tests/test_pairs.py checks jaxrt.pairs
# against, and netCDF4 (with cftime), which jax-md's own test module imports
# (tests/test_jax_md_acceptance.py). Run here once, in the project root:
#
#   bash benchmarks/gpu_extras.sh        # -> .gpu/extra/ (ignored by git, ~15 MB)
#
# then carry ".gpu/extra" beside ".gpu/p2" (64 MiB in all); run_pending_h200.sh
# installs them into /tmp/site when the folder is there.
set -euo pipefail
cd "$(dirname "$0")/.."
grep -qx '/.gpu/' .git/info/exclude 2>/dev/null || echo '/.gpu/' >> .git/info/exclude
mkdir -p .gpu/extra
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
  --implementation cp --platform manylinux_2_28_x86_64 \
  --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
  -d .gpu/extra ase netCDF4 cftime
du -sh .gpu/extra
