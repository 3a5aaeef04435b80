#!/usr/bin/env bash
# One-shot, idempotent setup: software Vulkan driver when no usable GPU driver exists (Debian 12),
# a virtualenv at .venv/, CPU torch when there is no NVIDIA GPU, then this package (+ extras); tmux with the dev extras.
# Usage: bash scripts/setup.sh [extras]   e.g. bash scripts/setup.sh dev,rl
set -euo pipefail
cd "$(dirname "$0")/.."
EXTRAS="${1:-}"
PY="${PYTHON:-python3}"
log() { printf '[setup] %s\n' "$*"; }
die() { printf '[setup] ERROR: %s\n' "$*" >&2; exit 1; }

command -v "$PY" >/dev/null || die "no $PY found; install Python >= 3.10 (Debian: apt-get install python3 python3-venv)"
"$PY" -c 'import sys; sys.exit(sys.version_info < (3, 10))' || die "Python >= 3.10 needed, found $("$PY" -V)"

has_nvidia() { command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; }

# ---------------------------------------------------------------- Vulkan (system)
ver_ge() { dpkg --compare-versions "$1" ge "$2"; }
mesa_version() { dpkg-query -W -f='${Version}' mesa-vulkan-drivers 2>/dev/null || true; }
need_vulkan_driver() {
    has_nvidia && return 1
    local v; v="$(mesa_version)"
    [ -n "$v" ] && ver_ge "$v" "24.3" && dpkg-query -W libvulkan1 >/dev/null 2>&1 && return 1
    return 0
}
if need_vulkan_driver; then
    if [ -r /etc/os-release ] && . /etc/os-release && [ "${ID:-}" = debian ] && [ "${VERSION_CODENAME:-}" = bookworm ]; then
        SUDO=""
        if [ "$(id -u)" != 0 ]; then
            command -v sudo >/dev/null && sudo -n true 2>/dev/null && SUDO="sudo -n" || die \
"SAPIEN needs Mesa >= 24.3 (lavapipe) on a machine without an NVIDIA GPU. As root run:
  printf 'Types: deb\nURIs: http://deb.debian.org/debian\nSuites: bookworm-backports\nComponents: main\nSigned-By: /usr/share/keyrings/debian-archive-keyring.gpg\n' > /etc/apt/sources.list.d/bookworm-backports.sources
  apt-get update && apt-get install -y -t bookworm-backports mesa-vulkan-drivers libvulkan1
then re-run this script."
        fi
        log "installing the software Vulkan driver (Mesa from bookworm-backports)"
        SRC=/etc/apt/sources.list.d/bookworm-backports.sources
        if ! grep -rqs "bookworm-backports" /etc/apt/sources.list /etc/apt/sources.list.d/; then
            URI="$(awk '/^URIs:/ {print $2; exit}' /etc/apt/sources.list.d/debian.sources 2>/dev/null || true)"
            printf 'Types: deb\nURIs: %s\nSuites: bookworm-backports\nComponents: main\nSigned-By: /usr/share/keyrings/debian-archive-keyring.gpg\n' \
                "${URI:-http://deb.debian.org/debian}" | $SUDO tee "$SRC" >/dev/null
        fi
        $SUDO apt-get update -qq
        DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq -t bookworm-backports mesa-vulkan-drivers libvulkan1 >/dev/null
        log "Mesa $(mesa_version) installed"
    else
        die "no usable Vulkan driver detected and this is not Debian 12. Install a Vulkan driver: the NVIDIA driver, or Mesa lavapipe >= 24.3 (package mesa-vulkan-drivers) and the Vulkan loader (libvulkan1); then re-run."
    fi
fi

# ---------------------------------------------------------------- system packages the extras' tests need
# apt_install PACKAGE WHY: installs a Debian package as root (or with password-less sudo); without apt, says
# what will not work
apt_install() {
    if command -v apt-get >/dev/null; then
        SUDO=""
        if [ "$(id -u)" != 0 ]; then
            command -v sudo >/dev/null && sudo -n true 2>/dev/null && SUDO="sudo -n" \
                || die "$2 needs $1; as root run: apt-get install -y $1, then re-run this script"
        fi
        log "installing $1 ($2)"
        $SUDO apt-get update -qq
        DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "$1" >/dev/null
    else
        log "$1 not found and no apt-get: $2 will not work (install $1)"
    fi
}

# the teleop tests drive `maniskill-irb120 teleop` through a real terminal with tmux send-keys
if [[ ",$EXTRAS," == *",dev,"* ]] && ! command -v tmux >/dev/null; then
    apt_install tmux "the teleop terminal test"
fi
# pyrealsense2's wheel links libusb-1.0 without shipping it; the librealsense tests (dev) import it too
if [[ ",$EXTRAS," == *",dev,"* || ",$EXTRAS," == *",real,"* ]] && command -v ldconfig >/dev/null \
    && ! ldconfig -p | grep -q "libusb-1.0.so.0"; then
    apt_install libusb-1.0-0 "pyrealsense2 (the RealSense camera)"
fi

# ---------------------------------------------------------------- Python environment
[ -x .venv/bin/python ] || { log "creating .venv"; "$PY" -m venv .venv; }
VPY=.venv/bin/python
if ! "$VPY" -c 'import torch' 2>/dev/null; then
    if has_nvidia; then
        log "NVIDIA GPU found: installing CUDA torch"; "$VPY" -m pip install -q torch
    else
        # never let a bare 'torch' requirement pull the multi-GB CUDA build onto a CPU-only machine
        log "no NVIDIA GPU: installing CPU torch==2.13.0"
        "$VPY" -m pip install -q torch==2.13.0 2>/dev/null \
            || "$VPY" -m pip install -q torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu
    fi
fi
SPEC="."
[ -n "$EXTRAS" ] && SPEC=".[$EXTRAS]"
STAMP=.venv/.maniskill_irb120-setup
WANT="$(cat pyproject.toml | sha256sum | cut -c1-16) $EXTRAS"
if [ ! -f "$STAMP" ] || [ "$(cat "$STAMP")" != "$WANT" ] || ! "$VPY" -c 'import maniskill_irb120' 2>/dev/null; then
    log "installing maniskill_irb120 $SPEC"
    "$VPY" -m pip install -q -e "$SPEC" 2>&1 | grep -v "is ignored: it is neither" || true
    "$VPY" -c 'import maniskill_irb120' || die "package install failed"
    echo "$WANT" > "$STAMP"
fi
log "ready ($("$VPY" -c 'import torch, mani_skill; print("torch", torch.__version__, "mani_skill", mani_skill.__version__)' 2>/dev/null))"
