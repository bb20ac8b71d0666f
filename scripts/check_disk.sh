#!/usr/bin/env bash
# Fails early, in one line, when a folder the install writes to has too little free disk.
# pip otherwise stops half-way through unpacking torch with "[Errno 28] No space left on device".
# usage: check_disk.sh NEED_MB DIR [DIR ...]   (a DIR that does not exist yet is checked at its parent)
set -euo pipefail
need_mb=$1
shift
for dir in "$@"; do
  probe=$dir
  while [ ! -d "$probe" ]; do probe=$(dirname "$probe"); done
  free_mb=$(df -Pm "$probe" | awk 'NR == 2 {print $4}')
  if [ "$free_mb" -lt "$need_mb" ]; then
    echo "setup: $dir needs about $need_mb MB of free disk for the install (torch and the project's packages); $probe has $free_mb MB free. Free some space (or point VENV / TMPDIR elsewhere) and run make again." >&2
    exit 1
  fi
done
