#!/usr/bin/env bash
# Print the path of a working Python 3.12 interpreter (lerobot 0.6 needs 3.12), or fail clearly.
set -u
candidates=("${PYTHON:-}" python3.12 /usr/bin/python3.12 /usr/local/bin/python3.12)
if command -v pyenv >/dev/null 2>&1; then
  for p in "$(pyenv root)"/versions/3.12*/bin/python3.12; do candidates+=("$p"); done
fi
for p in "$HOME"/.pyenv/versions/3.12*/bin/python3.12; do candidates+=("$p"); done
for c in "${candidates[@]}"; do
  [ -n "$c" ] || continue
  if "$c" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 12))' >/dev/null 2>&1; then
    command -v "$c" 2>/dev/null || echo "$c"
    exit 0
  fi
done
echo "error: Python 3.12 not found (lerobot 0.6 needs it). Install it (pyenv install 3.12," >&2
echo "       apt-get install python3.12, ...) or point PYTHON=/path/to/python3.12." >&2
exit 1
