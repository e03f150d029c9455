#!/usr/bin/env bash
# Installs the system packages lp3d needs (Debian/Ubuntu, as root): Mesa's lavapipe
# (software Vulkan) from bookworm-backports (Mesa 25.x, much faster than stock 22.x) where that
# suite exists, the Vulkan loader, Xvfb for viewer screenshots, and Debian's Chromium, whose
# headless WebGPU (SwiftShader) runs the `lp3d share` page in tests/view/test_share.py (~110 MB
# download). Idempotent. The backports entry is a copy of the machine's own
# Debian entry with a new suite name, so no mirror host is written here.
set -euo pipefail
export DEBIAN_FRONTEND=noninteractive
src=/etc/apt/sources.list.d/debian.sources
bp=/etc/apt/sources.list.d/lp3d-backports.sources
if [ -f "$src" ] && [ ! -f "$bp" ] && grep -q '^Suites:.*bookworm' "$src"; then
  # First stanza (the main archive), suite renamed.
  awk 'BEGIN{RS="";ORS="\n\n"} NR==1{print}' "$src" \
    | sed -E 's/^Suites:.*/Suites: bookworm-backports/' > "$bp"
fi
# winit (the viewer) loads the X11 client libraries at run time.
need=(mesa-vulkan-drivers libvulkan1 xvfb xauth libx11-6 libx11-xcb1 libxcursor1 libxrandr2 libxi6 libxkbcommon-x11-0)
missing=()
for p in "${need[@]}"; do dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p"); done
# Upgrade to the backports Mesa when it is not installed yet.
if [ -f "$bp" ] && ! dpkg -s mesa-vulkan-drivers 2>/dev/null | grep -q '^Version: 2[5-9]'; then
  missing+=(mesa-vulkan-drivers)
fi
if [ ${#missing[@]} -gt 0 ]; then
  apt-get update -qq
  if [ -f "$bp" ]; then
    apt-get install -y -qq -t bookworm-backports "${missing[@]}" || apt-get install -y -qq "${missing[@]}"
  else
    apt-get install -y -qq "${missing[@]}"
  fi
fi
# Chromium for tests/view/test_share.py, on its own: Debian has the package, Ubuntu's is a snap stub, and
# a machine without it should still get everything else (the test then fails saying what is missing).
if ! dpkg -s chromium >/dev/null 2>&1; then
  [ ${#missing[@]} -gt 0 ] || apt-get update -qq
  apt-get install -y -qq chromium || echo "warning: no chromium package; tests/view/test_share.py needs Chromium" >&2
fi
echo "mesa-vulkan-drivers $(dpkg-query -W -f='${Version}' mesa-vulkan-drivers)"
echo "chromium $(dpkg-query -W -f='${Version}' chromium 2>/dev/null || echo 'not installed')"
