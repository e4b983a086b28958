#!/usr/bin/env bash
# Install h3edge as a systemd service on a Jetson (JetPack 5/6). Run as root from the repository:
#   sudo deploy/install-jetson.sh [PROFILE.toml] [ZENOH.json5]
# - system user h3edge (groups video, plugdev: GPU device nodes, the OAK)
# - /opt/h3edge/venv with --system-site-packages, so JetPack's CUDA torch is used (pip does not
#   replace it: torch's range in pyproject.toml is loose on purpose)
# - the OAK udev rule, /etc/h3edge/{profile.toml,zenoh.json5}, the unit, enabled and started
set -euo pipefail
SRC="$(cd "$(dirname "$0")/.." && pwd)"
PROFILE="${1:-$SRC/profiles/x86-cpu.toml}"
ZCONF="${2:-$SRC/deploy/zenoh-peer.json5}"
[ "$(id -u)" -eq 0 ] || { echo "run as root (sudo)" >&2; exit 1; }
python3 -c "import torch; print('system torch', torch.__version__, 'cuda', torch.cuda.is_available())" \
  || { echo "install NVIDIA's JetPack torch wheel first (https://docs.nvidia.com/deeplearning/frameworks/install-pytorch-jetson-platform/)" >&2; exit 1; }

id h3edge >/dev/null 2>&1 || useradd --system --home-dir /var/lib/h3edge --shell /usr/sbin/nologin h3edge
getent group plugdev >/dev/null || groupadd --system plugdev
usermod -a -G video,plugdev h3edge

install -d -o root -g root /opt/h3edge
rm -rf /opt/h3edge/src && cp -a "$SRC" /opt/h3edge/src
python3 -m venv --system-site-packages /opt/h3edge/venv
/opt/h3edge/venv/bin/pip install -q --upgrade pip
/opt/h3edge/venv/bin/pip install -q "/opt/h3edge/src[oak]"

install -D -m 0644 "$SRC/deploy/80-movidius.rules" /etc/udev/rules.d/80-movidius.rules
udevadm control --reload-rules && udevadm trigger || true

install -d -m 0755 /etc/h3edge
[ -e /etc/h3edge/profile.toml ] || install -m 0644 "$PROFILE" /etc/h3edge/profile.toml
[ -e /etc/h3edge/zenoh.json5 ] || install -m 0640 -g h3edge "$ZCONF" /etc/h3edge/zenoh.json5
[ -e /etc/default/h3edge ] || echo 'H3EDGE_ARGS=""' > /etc/default/h3edge

install -m 0644 "$SRC/systemd/h3edge.service" /etc/systemd/system/h3edge.service
systemd-analyze verify /etc/systemd/system/h3edge.service || true
systemctl daemon-reload
systemctl enable --now h3edge.service
systemctl --no-pager status h3edge.service | head -n 5
echo "query it: /opt/h3edge/venv/bin/h3edge query status --zenoh-config /etc/h3edge/zenoh.json5"
# the OAK camera source: installed, started only where the camera is (H3EDGE_OAK_ARGS in /etc/default/h3edge)
install -m 0644 "$SRC/systemd/h3edge-oak.service" /etc/systemd/system/h3edge-oak.service
systemd-analyze verify /etc/systemd/system/h3edge-oak.service || true
echo "with an OAK attached: systemctl enable --now h3edge-oak.service"
