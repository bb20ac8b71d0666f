#!/usr/bin/env bash
# Installs the Debian libraries the Python wheels need but do not ship:
#   libusb-1.0-0      open3d's native module links it
#   libegl1, libgl1, libgl1-mesa-dri   headless OpenGL through EGL (Mesa llvmpipe) for moderngl
#   xvfb, xauth       a virtual X server for the preview window test
#   icc-profiles-free real-world ICC profiles (Adobe RGB-compatible, a v4 sRGB) the photo decoder's tests read
# As root it installs what is missing with apt; otherwise it prints the exact command and fails.
set -euo pipefail
pkgs=(libusb-1.0-0 libegl1 libgl1 libgl1-mesa-dri xvfb xauth icc-profiles-free)
missing=()
for p in "${pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
[ ${#missing[@]} -eq 0 ] && exit 0
if ! command -v apt-get >/dev/null 2>&1; then
  echo "sysdeps: missing system libraries ${missing[*]} and no apt-get here; install them with your package manager" >&2
  exit 1
fi
cmd="apt-get install -y --no-install-recommends ${missing[*]}"
if [ "$(id -u)" -eq 0 ]; then
  echo "sysdeps: installing ${missing[*]}"
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq >/dev/null
  $cmd >/dev/null
else
  echo "sysdeps: missing system libraries. Run as root:" >&2
  echo "  sudo apt-get update && sudo $cmd" >&2
  exit 1
fi
