#!/usr/bin/env bash
# Remove what deploy/install.sh installed: stops and disables the topseg units, removes them,
# the udev rules and /opt/topseg. Keeps /etc/topseg (your configs and certificates), the
# service state in /var/lib/topseg and the topseg user unless --purge. Idempotent: says
# what it removed and what was already gone.
#
#   sudo deploy/uninstall.sh [--root DIR] [--no-systemctl] [--purge]
#
#   --root DIR       uninstall from DIR instead of / (also $DESTDIR)
#   --no-systemctl   do not stop units or run systemctl daemon-reload / udevadm control --reload
#   --purge          also remove /etc/topseg, /var/lib/topseg, /var/cache/topseg and the user
set -euo pipefail

ROOT=${DESTDIR:-}
SYSTEMCTL=1
PURGE=0

usage() { sed -n '2,/^set -euo/p' "$0" | sed '$d; s/^# \{0,1\}//'; }
die() { echo "uninstall: error: $*" >&2; exit 2; }

while [ $# -gt 0 ]; do
    case $1 in
        --root) [ $# -ge 2 ] || die "--root needs a directory"; ROOT=$2; shift ;;
        --root=*) ROOT=${1#*=} ;;
        --no-systemctl) SYSTEMCTL=0 ;;
        --purge) PURGE=1 ;;
        -h|--help) usage; exit 0 ;;
        *) die "unknown argument $1 (see --help)" ;;
    esac
    shift
done
if [ -n "$ROOT" ]; then
    [ -d "$ROOT" ] || die "$ROOT is not a directory"
    ROOT=$(cd "$ROOT" && pwd)
    [ "$ROOT" = / ] && ROOT=""
fi
if [ -z "$ROOT" ] && [ "$(id -u)" -ne 0 ]; then
    die "uninstalling from / needs root (sudo $0), or use --root DIR"
fi

say() { echo "uninstall: $*"; }
SYSTEMD_LIVE=0
if [ -z "$ROOT" ] && [ "$SYSTEMCTL" = 1 ] && command -v systemctl >/dev/null \
    && [ -d /run/systemd/system ]; then
    SYSTEMD_LIVE=1
fi

remove() {  # PATH...: files or directories
    local path
    for path in "$@"; do
        if [ -e "$path" ] || [ -L "$path" ]; then
            rm -rf -- "$path"
            say "removed ${path#"$ROOT"}"
        else
            say "already gone ${path#"$ROOT"}"
        fi
    done
}

# 1. Stop the running units (every instance), then disable them by their symlinks.
if [ "$SYSTEMD_LIVE" = 1 ]; then
    running=$(systemctl list-units --all --plain --no-legend 'topseg-*' | awk '{print $1}')
    if [ -n "$running" ]; then
        # shellcheck disable=SC2086
        systemctl stop $running
        say "stopped $(echo $running)"
    fi
fi
shopt -s nullglob
links=("$ROOT"/etc/systemd/system/*.wants/topseg-*.service)
units=("$ROOT"/etc/systemd/system/topseg-*.service)
shopt -u nullglob
if [ ${#links[@]} -gt 0 ]; then
    rm -f -- "${links[@]}"
    say "disabled ${#links[@]} unit instance(s)"
fi
if [ ${#units[@]} -gt 0 ]; then
    remove "${units[@]}"
else
    say "already gone topseg units in /etc/systemd/system"
fi
remove "$ROOT/etc/udev/rules.d/99-topseg.rules" "$ROOT/opt/topseg"

# 2. Configs, state and the user: only with --purge.
if [ "$PURGE" = 1 ]; then
    remove "$ROOT/etc/topseg" "$ROOT/var/lib/topseg" "$ROOT/var/cache/topseg"
    if [ -z "$ROOT" ]; then
        if getent passwd topseg >/dev/null; then
            userdel topseg
            say "removed user topseg"
        else
            say "already gone user topseg"
        fi
    fi
else
    if [ -d "$ROOT/etc/topseg" ]; then
        say "kept /etc/topseg (your configs; --purge removes them)"
    fi
    if [ -z "$ROOT" ] && getent passwd topseg >/dev/null; then
        say "kept user topseg (--purge removes it)"
    fi
fi

# 3. Tell systemd and udev.
if [ "$SYSTEMD_LIVE" = 1 ]; then
    systemctl daemon-reload
    systemctl reset-failed 'topseg-*' 2>/dev/null || true
    say "ran systemctl daemon-reload"
    if command -v udevadm >/dev/null && udevadm control --reload 2>/dev/null; then
        say "ran udevadm control --reload"
    fi
else
    say "skipped systemctl daemon-reload and udevadm control --reload"
fi
say "done"
