#!/usr/bin/env bash
# Debian libraries that the Python wheels need but do not ship:
# EGL + Mesa for MuJoCo's offscreen rendering (MUJOCO_GL=egl), libgomp for OpenCV/Open3D,
# libusb for open3d's import (it loads libusb-1.0 at import time). Installs only what is missing.
set -euo pipefail
packages=(libegl1 libegl-mesa0 libgl1-mesa-dri libgomp1 libusb-1.0-0)
missing=()
for p in "${packages[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
[ ${#missing[@]} -eq 0 ] && exit 0
echo "installing Debian packages: ${missing[*]}"
sudo_cmd=""
[ "$(id -u)" -eq 0 ] || sudo_cmd="sudo"
export DEBIAN_FRONTEND=noninteractive
$sudo_cmd apt-get update -qq
$sudo_cmd apt-get install -y -qq --no-install-recommends "${missing[@]}"
