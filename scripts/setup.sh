#!/usr/bin/env bash
# Installs what rtstream needs on a Debian 12 (bookworm) machine, only what is missing; does
# nothing (and needs no network) when everything is present. Non-interactive; uses sudo when not
# root. Called by scripts/run.sh and scripts/test.sh.
#
#   mesa-vulkan-drivers >= 25 from bookworm-backports: lavapipe with VK_KHR_acceleration_structure
#                              and VK_KHR_ray_query (bookworm's own 22.3 has no ray tracing)
#   libvulkan1, vulkan-validationlayers: the loader and the Khronos validation layer (tests)
#   glslc:                     compiles renderer/shaders at build time
#   assimp-testmodels:         real glTF 2.0 test assets (and broken ones) under /usr/share/assimp
set -euo pipefail

have_pkg() { dpkg-query -W -f='${Status}' "$1" 2>/dev/null | grep -q "install ok installed"; }
mesa_ok() {
  local v
  v=$(dpkg-query -W -f='${Version}' mesa-vulkan-drivers 2>/dev/null) || return 1
  have_pkg mesa-vulkan-drivers && dpkg --compare-versions "$v" ge 25
}

missing=()
for p in libvulkan1 vulkan-validationlayers glslc assimp-testmodels; do
  have_pkg "$p" || missing+=("$p")
done
need_mesa=0
mesa_ok || need_mesa=1

if ! command -v cargo >/dev/null 2>&1; then
  echo "setup: cargo is not on PATH; install a Rust toolchain (rustup) first" >&2
  exit 1
fi
if [ ${#missing[@]} -eq 0 ] && [ $need_mesa -eq 0 ]; then
  exit 0
fi

SUDO=""
if [ "$(id -u)" -ne 0 ]; then
  command -v sudo >/dev/null 2>&1 || { echo "setup: need root or sudo to install: ${missing[*]} mesa-vulkan-drivers" >&2; exit 1; }
  SUDO="sudo -n"
fi
export DEBIAN_FRONTEND=noninteractive

if [ $need_mesa -eq 1 ] && ! grep -rqs "bookworm-backports" /etc/apt/sources.list /etc/apt/sources.list.d/; then
  echo "setup: adding the bookworm-backports suite"
  echo "deb http://deb.debian.org/debian bookworm-backports main" | $SUDO tee /etc/apt/sources.list.d/bookworm-backports.list >/dev/null
fi
echo "setup: installing ${missing[*]}$([ $need_mesa -eq 1 ] && echo ' mesa-vulkan-drivers (bookworm-backports)')"
$SUDO apt-get update -qq
if [ ${#missing[@]} -gt 0 ]; then
  $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi
if [ $need_mesa -eq 1 ]; then
  $SUDO apt-get install -y -qq --no-install-recommends -t bookworm-backports mesa-vulkan-drivers >/dev/null
fi
mesa_ok || { echo "setup: mesa-vulkan-drivers >= 25 did not install" >&2; exit 1; }
echo "setup: done"
