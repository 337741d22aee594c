#!/usr/bin/env bash
# Makes sure a Vulkan driver is present for the GPU tests: a real GPU's, or else Debian's
# mesa-vulkan-drivers (lavapipe, a software Vulkan device on the CPU), installed when this runs
# as root with apt. Prints what it found; exits 0 when a Vulkan driver is present, 1 otherwise.
set -uo pipefail
have_icd() {
  local icds
  icds=$(find /usr/share/vulkan/icd.d /etc/vulkan/icd.d -name '*.json' 2>/dev/null | wc -l)
  [ "$icds" -gt 0 ] && ldconfig -p | grep 'libvulkan\.so\.1' >/dev/null
}
if have_icd; then
  echo "gpu: Vulkan driver present ($(find /usr/share/vulkan/icd.d /etc/vulkan/icd.d -name '*.json' -printf '%f ' 2>/dev/null))"
  exit 0
fi
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
  echo "gpu: no Vulkan driver; installing Debian's mesa-vulkan-drivers (lavapipe) ..."
  export DEBIAN_FRONTEND=noninteractive
  apt-get install -y -qq mesa-vulkan-drivers libvulkan1 >/dev/null 2>&1 \
    || { apt-get update -qq >/dev/null 2>&1; apt-get install -y -qq mesa-vulkan-drivers libvulkan1 >/dev/null 2>&1; }
fi
if have_icd; then
  echo "gpu: Vulkan driver installed"
  exit 0
fi
echo "gpu: no Vulkan driver (install mesa-vulkan-drivers or a GPU driver); the GPU tests will say SKIPPED"
exit 1
