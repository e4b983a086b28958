#!/usr/bin/env bash
# Install h3edge as a systemd service on a Jetson (JetPack 6: Ubuntu 22.04, Python 3.10, CUDA).
# Run as root from the repository:
#   sudo deploy/install-jetson.sh [PROFILE] [ZENOH.json5]
# - PROFILE: a shipped profile name or a TOML path; default: from /proc/device-tree/model
#   (AGX Orin -> orin-agx, Orin NX -> orin-nx, Orin Nano -> orin-nano)
# - system user h3edge (groups video, plugdev: GPU device nodes, the OAK)
# - /opt/h3edge/venv with --system-site-packages, so JetPack's CUDA torch is used (pip does not
#   replace it: torch's range in pyproject.toml is loose on purpose), and a system onnxruntime-gpu
#   (NVIDIA's Jetson build, with the TensorRT / CUDA providers) stays visible: the CPU-only wheel
#   is installed into the venv only when no onnxruntime is importable from the system
# - the OAK udev rule, /etc/h3edge/{profile.toml,zenoh.json5}, the unit with a memory drop-in
#   sized from the profile's budget + the runtime's cost measured here, enabled and started
set -euo pipefail
SRC="$(cd "$(dirname "$0")/.." && pwd)"
PROFILE_ARG="${1:-}"
ZCONF="${2:-$SRC/deploy/zenoh-peer.json5}"
VENV=/opt/h3edge/venv
[ "$(id -u)" -eq 0 ] || { echo "run as root (sudo)" >&2; exit 1; }
python3 -c 'import sys; assert sys.version_info >= (3, 10), sys.version' \
  || { echo "h3edge needs Python >= 3.10 (JetPack 6); JetPack 5's Python 3.8 is not supported" >&2; exit 1; }
python3 -c "import torch; print('system torch', torch.__version__, 'cuda', torch.cuda.is_available())" \
  || { echo "install NVIDIA's JetPack torch wheel first (https://docs.nvidia.com/deeplearning/frameworks/install-pytorch-jetson-platform/)" >&2; exit 1; }

id h3edge >/dev/null 2>&1 || useradd --system --home-dir /var/lib/h3edge --shell /usr/sbin/nologin h3edge
getent group plugdev >/dev/null || groupadd --system plugdev
usermod -a -G video,plugdev h3edge

install -d -o root -g root /opt/h3edge
rm -rf /opt/h3edge/src && cp -a "$SRC" /opt/h3edge/src
python3 -m venv --system-site-packages "$VENV"
"$VENV/bin/pip" install -q --upgrade pip
if python3 -c "import onnxruntime" 2>/dev/null; then
  # keep the system build (onnxruntime-gpu): install h3edge's other requirements, not the CPU wheel
  echo "system onnxruntime: $(python3 -c 'import onnxruntime as o; print(o.__version__, o.get_available_providers())')"
  "$VENV/bin/pip" install -q --no-deps "/opt/h3edge/src"
  "$VENV/bin/python" - <<'EOF' > /opt/h3edge/requirements.txt
from importlib import metadata
try:
    from packaging.requirements import Requirement
except ImportError:  # the venv has pip's copy
    from pip._vendor.packaging.requirements import Requirement
for r in metadata.requires("h3edge") or []:
    req = Requirement(r)
    if req.name in ("torch", "onnxruntime") or (req.marker and not req.marker.evaluate({"extra": "oak"})):
        continue
    print(r)
EOF
  "$VENV/bin/pip" install -q -r /opt/h3edge/requirements.txt
else
  "$VENV/bin/pip" install -q "/opt/h3edge/src[oak]"
fi

install -D -m 0644 "$SRC/deploy/80-movidius.rules" /etc/udev/rules.d/80-movidius.rules
udevadm control --reload-rules && udevadm trigger || true

# profile and memory limits: measured on this device (exit 2 with a reason when it does not fit)
PLAN="$("$VENV/bin/h3edge" deploy plan ${PROFILE_ARG:+--profile "$PROFILE_ARG"})"
eval "$PLAN"
echo "$PLAN"
install -d -m 0755 /etc/h3edge
[ -e /etc/h3edge/profile.toml ] || install -m 0644 "$PROFILE_FILE" /etc/h3edge/profile.toml
[ -e /etc/h3edge/zenoh.json5 ] || install -m 0640 -g h3edge "$ZCONF" /etc/h3edge/zenoh.json5
[ -e /etc/default/h3edge ] || echo 'H3EDGE_ARGS=""' > /etc/default/h3edge

install -m 0644 "$SRC/systemd/h3edge.service" /etc/systemd/system/h3edge.service
install -d -m 0755 /etc/systemd/system/h3edge.service.d
cat > /etc/systemd/system/h3edge.service.d/memory.conf <<EOF
# written by deploy/install-jetson.sh for $PROFILE on ${DEVICE_MODEL:-this device}:
# budget ${BUDGET_MB} MB + runtime ${RUNTIME_MB} MB (measured at install) + headroom
[Service]
MemoryHigh=$MEMORY_HIGH
MemoryMax=$MEMORY_MAX
EOF
systemd-analyze verify /etc/systemd/system/h3edge.service || true
systemctl daemon-reload
systemctl enable --now h3edge.service
systemctl --no-pager status h3edge.service | head -n 5
echo "query it: $VENV/bin/h3edge query status --zenoh-config /etc/h3edge/zenoh.json5"
# the OAK camera source: installed, started only where the camera is (H3EDGE_OAK_ARGS in /etc/default/h3edge)
install -m 0644 "$SRC/systemd/h3edge-oak.service" /etc/systemd/system/h3edge-oak.service
systemd-analyze verify /etc/systemd/system/h3edge-oak.service || true
echo "with an OAK attached: systemctl enable --now h3edge-oak.service"
