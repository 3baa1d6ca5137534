#!/usr/bin/env bash
# Builds the second Python environment the `sam` segmenter runs in (graph field `python:`).
#
# segment-anything imports torchvision, and torchvision 0.29.1 needs torch 2.14.1, while the main
# environment pins the CPU torch 2.13.0. This venv holds torch 2.14.1 + torchvision 0.29.1 (from the
# machine's local wheel cache), segment-anything (PyPI) and the umad package itself, installed with
# --no-deps so its torch pin does not pull 2.13.0 back in; the package's other dependencies (and its
# test extra) are read from the installed package's metadata and installed explicitly.
#
# Usage: bash sam_env.sh [VENV_DIR] [UMAD_SOURCE]
#   VENV_DIR     default .venv-sam in the working folder (what `umad eval --sam-python` expects)
#   UMAD_SOURCE  the umad checkout (installed editable) or wheel to install there; default the
#                checkout this script lies in. Shipped in the package: `umad eval --help` prints its path.
# Prints the venv's python path on its last line. Re-running on a finished venv only re-checks it.
set -euo pipefail

script_checkout="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
venv_dir="${1:-.venv-sam}"
umad_source="${2:-$script_checkout}"
python_bin="${PYTHON:-python3.11}"
torch_version="2.14.1"
torchvision_version="0.29.1"

if [[ -d "$umad_source" && -f "$umad_source/pyproject.toml" ]]; then
    umad_install=(-e "$umad_source")
elif [[ -f "$umad_source" && "$umad_source" == *.whl ]]; then
    umad_install=("$umad_source")
else
    echo "sam_env.sh: UMAD_SOURCE $umad_source: expected a umad checkout (a folder with pyproject.toml) or a umad wheel (.whl)" >&2
    exit 2
fi

if [[ ! -x "$venv_dir/bin/python" ]]; then
    "$python_bin" -m venv "$venv_dir"
fi
venv_python="$venv_dir/bin/python"

installed_torch="$("$venv_python" -c 'import torch; print(torch.__version__.split("+")[0])' 2>/dev/null || true)"
if [[ "$installed_torch" != "$torch_version" ]]; then
    "$venv_python" -m pip install --quiet "torch==$torch_version" "torchvision==$torchvision_version"
fi

"$venv_python" -m pip install --quiet --no-deps "${umad_install[@]}"

# The package's declared dependencies minus torch (pinned differently here), plus its test extra.
mapfile -t other_deps < <("$venv_python" - <<'PY'
import re
from importlib.metadata import requires

for requirement in requires("umad"):
    spec, _, marker = requirement.partition(";")
    if marker and "extra == \"test\"" not in marker:
        continue
    if re.split(r"[<>=!~\[ ]", spec, maxsplit=1)[0].strip().lower() != "torch":
        print(spec.strip())
PY
)
"$venv_python" -m pip install --quiet "${other_deps[@]}" segment-anything \
    "torch==$torch_version" "torchvision==$torchvision_version"

"$venv_python" -c "
import segment_anything, torch, torchvision, umad_common
assert torch.__version__.split('+')[0] == '$torch_version', torch.__version__
print('sam env ok: torch', torch.__version__, 'torchvision', torchvision.__version__)
"
echo "$venv_python"
