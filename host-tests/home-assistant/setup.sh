#!/usr/bin/env bash
# Makes (or reuses) the virtual environment with the pinned Home Assistant of
# requirements.txt, and prints its python. Home Assistant 2025.4 needs Python
# 3.13: the first of $TINYBMS_HA_PYTHON, python3.13 on PATH, pyenv's 3.13.
# The environment is cached outside the clone, keyed by requirements.txt
# ($TINYBMS_HA_VENV overrides the place).
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
req="$here/requirements.txt"
key="$(sha256sum "$req" | cut -c1-12)"
venv="${TINYBMS_HA_VENV:-${XDG_CACHE_HOME:-$HOME/.cache}/tinybms/home-assistant-$key}"
if [ -x "$venv/bin/python" ] && [ -f "$venv/.complete" ]; then
    echo "$venv/bin/python"
    exit 0
fi
py=""
for c in "${TINYBMS_HA_PYTHON:-}" python3.13 "$HOME"/.pyenv/versions/3.13*/bin/python3.13; do
    if [ -n "$c" ] && command -v "$c" >/dev/null 2>&1 \
        && "$c" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 13))' 2>/dev/null; then
        py="$c"
        break
    fi
done
if [ -z "$py" ]; then
    echo "setup.sh: Home Assistant 2025.4 needs Python 3.13: none found (set TINYBMS_HA_PYTHON)" >&2
    exit 1
fi
rm -rf "$venv"
mkdir -p "$(dirname "$venv")"
"$py" -m venv "$venv" >&2
"$venv/bin/python" -m pip install --quiet --disable-pip-version-check -r "$req" >&2
touch "$venv/.complete"
echo "$venv/bin/python"
