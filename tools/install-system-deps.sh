#!/usr/bin/env bash
# System packages the tests use, installed by the project itself (CI machines start bare).
# Where we are not root or apt is missing, say so and go on: the tests that need a package skip
# with that reason.
set -u
PACKAGES=(
  user-mode-linux kmod iproute2   # SocketCAN tests: a kernel with vcan in user-mode Linux (tools/uml);
                                  # iproute2 also: network-namespace hosts (tests/test_deployment.py, `ip`, `ss`)
  can-utils                       # cansend/canplayer against the board in UML (tests/test_kernel_can_uml.py)
  chromium                        # report rendering test (tests/test_report_render.py)
)
[ ${#PACKAGES[@]} -eq 0 ] && exit 0
missing=()
for p in "${PACKAGES[@]}"; do dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p"); done
[ ${#missing[@]} -eq 0 ] && exit 0
if [ "$(id -u)" != 0 ] || ! command -v apt-get >/dev/null; then
  echo "install-system-deps: not root or no apt-get; missing: ${missing[*]} (tests that need them will skip)"
  exit 0
fi
echo "install-system-deps: installing ${missing[*]}"
export DEBIAN_FRONTEND=noninteractive
apt-get update -qq >/dev/null && apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null \
  || echo "install-system-deps: apt-get failed; tests that need ${missing[*]} will skip"
exit 0
