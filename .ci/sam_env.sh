#!/usr/bin/env bash
# Builds the second Python environment the `sam` segmenter runs in (graph field `python:`).
#
# segment-anything imports torchvision, and torchvision 0.29.1 needs torch 2.14.1, while the main
# environment pins the CPU torch 2.13.0. This venv holds torch 2.14.1 + torchvision 0.29.1 (from the
# machine's local wheel cache), segment-anything (PyPI) and the umad package itself, installed
# editable with --no-deps so its torch pin does not pull 2.13.0 back in; the package's other
# dependencies are read from pyproject.toml and installed explicitly.
#
# Usage: .ci/sam_env.sh [VENV_DIR]   (default: .venv-sam in the repository root)
# Prints the venv's python path on its last line. Re-running on a finished venv only re-checks it.
set -euo pipefail

repo_root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv_dir="${1:-$repo_root/.venv-sam}"
python_bin="${PYTHON:-python3.11}"
torch_version="2.14.1"
torchvision_version="0.29.1"

if [[ ! -x "$venv_dir/bin/python" ]]; then
    "$python_bin" -m venv "$venv_dir"
fi
venv_python="$venv_dir/bin/python"

installed_torch="$("$venv_python" -c 'import torch; print(torch.__version__.split("+")[0])' 2>/dev/null || true)"
if [[ "$installed_torch" != "$torch_version" ]]; then
    "$venv_python" -m pip install --quiet "torch==$torch_version" "torchvision==$torchvision_version"
fi

# The package's declared dependencies minus torch (pinned differently here), plus the test runner.
mapfile -t other_deps < <("$venv_python" - "$repo_root/pyproject.toml" <<'PY'
import re
import sys
import tomllib

with open(sys.argv[1], "rb") as f:
    project = tomllib.load(f)["project"]
for requirement in project["dependencies"]:
    if re.split(r"[<>=!~\[; ]", requirement, maxsplit=1)[0].strip().lower() != "torch":
        print(requirement)
for requirement in project.get("optional-dependencies", {}).get("test", []):
    print(requirement)
PY
)
"$venv_python" -m pip install --quiet "${other_deps[@]}" segment-anything \
    "torch==$torch_version" "torchvision==$torchvision_version"
"$venv_python" -m pip install --quiet --no-deps -e "$repo_root"

"$venv_python" -c "
import segment_anything, torch, torchvision, umad_common
assert torch.__version__.split('+')[0] == '$torch_version', torch.__version__
print('sam env ok: torch', torch.__version__, 'torchvision', torchvision.__version__)
"
echo "$venv_python"
