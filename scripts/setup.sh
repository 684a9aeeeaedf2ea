#!/usr/bin/env bash
# Set up (or reuse) the project's virtual environment in .venv: torch==2.13.0 (CPU) first, then
# qtl with its dev extras, then qtl's native kernels into the per-user cache (gcc; optional). Idempotent:
# a second run installs and compiles nothing when nothing changed.
#   --mujoco     also the `mujoco` extra (gymnasium's MuJoCo envs, task=inverted_pendulum);
#   --launchers  also the `ray` and `slurm` extras (hydra/launcher=ray|slurm|slurm_local; tests/test_launchers.py).
# A later run without a flag keeps what is installed.
set -euo pipefail
cd "$(dirname "$0")/.."

mujoco=0
launchers=0
for arg in "$@"; do
  case "$arg" in
    --mujoco) mujoco=1 ;;
    --launchers) launchers=1 ;;
    *) echo "usage: bash scripts/setup.sh [--mujoco] [--launchers]" >&2; exit 2 ;;
  esac
done

python=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$python" -c 'import sys; sys.exit(sys.version_info < (3, 10))' \
    || { echo "qtl needs Python >= 3.10 (found $("$python" --version 2>&1))" >&2; exit 1; }
  "$python" -m venv .venv
fi
pip=(.venv/bin/python -m pip --disable-pip-version-check --quiet)

# torch first and pinned: an unpinned torch resolved by pip downloads several GB of CUDA packages.
if ! .venv/bin/python -c 'import sys, torch; sys.exit(torch.__version__.split("+")[0] != "2.13.0")' 2>/dev/null; then
  "${pip[@]}" install torch==2.13.0
fi

# The project itself, editable, reinstalled only when pyproject.toml changed (or a flag asks for an extra that
# does not import yet).
stamp=.venv/.qtl-installed
want=$(sha256sum pyproject.toml | cut -d' ' -f1)
extras=dev
missing_extra=0
if [ "$mujoco" = 1 ]; then
  extras=$extras,mujoco
  .venv/bin/python -c 'import mujoco' 2>/dev/null || missing_extra=1
fi
if [ "$launchers" = 1 ]; then
  extras=$extras,ray,slurm
  .venv/bin/python -c 'import hydra_plugins.hydra_ray_launcher, hydra_plugins.hydra_submitit_launcher' 2>/dev/null \
    || missing_extra=1
fi
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ] || [ "$missing_extra" = 1 ] \
    || ! .venv/bin/python -c 'import qtl, qtl.envs' 2>/dev/null; then
  "${pip[@]}" install -e ".[$extras]"
  echo "$want" > "$stamp"
fi

# The native kernels (the C sources of qtl/kernels/native/, one library), compiled ahead of their first use into the
# per-user cache ($QTL_CACHE_DIR, else $XDG_CACHE_HOME/qtl, else ~/.cache/qtl), once per source, compiler, flags and
# CPU. Optional: qtl would compile them on first use anyway, and without a compiler it uses the torch path; a failed
# build says so in one line.
.venv/bin/python -m qtl.kernels.native.build --optional \
  || echo "qtl: native kernels not built; qtl will use the torch path" >&2
