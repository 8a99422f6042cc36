#!/usr/bin/env bash
# Install topseg as a service on a cell PC: the `topseg` system user, topseg in its own venv
# (/opt/topseg/venv), the bundled model and demo recording, the systemd units, the udev rules,
# the Zenoh configs (/etc/topseg/zenoh/) and example service configs (/etc/topseg/*.toml).
# Idempotent: a second run changes nothing. Configs an operator has edited are kept (the new
# default goes beside them as FILE.dist). Says what it did, one line per item.
# Enables nothing: see docs/howto/deploy.md for the next steps.
#
#   sudo deploy/install.sh [--root DIR] [--no-systemctl] [--python PY] [--extras LIST]
#                          [--source PATH] [--pip-args "ARGS"]
#
#   --root DIR       install under DIR instead of / (also $DESTDIR): for tests and inspection.
#                    No user is created, nothing is reloaded, and the venv's scripts point
#                    into DIR (a venv cannot be moved).
#   --no-systemctl   do not run systemctl daemon-reload / udevadm control --reload
#   --python PY      the Python (>= 3.11) that makes the venv (default: python3)
#   --extras LIST    pip extras besides cell (the live services, always installed), comma-
#                    separated: the sensors' SDKs, e.g. oak or kinect,openni2 (default: kinect
#                    when libfreenect-dev is installed, openni2 when libopenni2 is)
#   --source PATH    what pip installs (default: this checkout); a wheel works too
#   --pip-args ARGS  more pip install arguments (e.g. "--no-deps --no-index" for offline tests)
#   --no-venv-pip    make the venv without pip and install with --python's pip (faster; tests)
#   --no-compile     do not compile numba's kernels into the services' cache now (the worker
#                    then compiles them on its first start: ~1-2 min on 2 cores)
set -euo pipefail

CHECKOUT=$(cd "$(dirname "$0")/.." && pwd)
ROOT=${DESTDIR:-}
SYSTEMCTL=1
PYTHON=python3
EXTRAS=auto
SOURCE=$CHECKOUT
PIP_ARGS=""
VENV_PIP=1
COMPILE=1

usage() { sed -n '2,/^set -euo/p' "$0" | sed '$d; s/^# \{0,1\}//'; }
die() { echo "install: error: $*" >&2; exit 2; }

while [ $# -gt 0 ]; do
    case $1 in
        --root) [ $# -ge 2 ] || die "--root needs a directory"; ROOT=$2; shift ;;
        --root=*) ROOT=${1#*=} ;;
        --no-systemctl) SYSTEMCTL=0 ;;
        --python) [ $# -ge 2 ] || die "--python needs a program"; PYTHON=$2; shift ;;
        --extras) [ $# -ge 2 ] || die "--extras needs a list"; EXTRAS=$2; shift ;;
        --source) [ $# -ge 2 ] || die "--source needs a path"; SOURCE=$2; shift ;;
        --pip-args) [ $# -ge 2 ] || die "--pip-args needs arguments"; PIP_ARGS=$2; shift ;;
        --no-venv-pip) VENV_PIP=0 ;;
        --no-compile) COMPILE=0 ;;
        -h|--help) usage; exit 0 ;;
        *) die "unknown argument $1 (see --help)" ;;
    esac
    shift
done
if [ -n "$ROOT" ]; then
    mkdir -p "$ROOT" || die "cannot create $ROOT"
    ROOT=$(cd "$ROOT" && pwd)
    [ "$ROOT" = / ] && ROOT=""
fi
if [ -z "$ROOT" ] && [ "$(id -u)" -ne 0 ]; then
    die "installing into / needs root (sudo $0), or use --root DIR"
fi

say() { echo "install: $*"; }
OPT=$ROOT/opt/topseg
ETC=$ROOT/etc/topseg
RECORD=$ETC/.installed-defaults.sha256  # the defaults this script last wrote to /etc/topseg

sha() { sha256sum "$1" | cut -d' ' -f1; }

# A file that the package owns: replaced whenever it differs.
install_file() {  # SRC DEST MODE
    local src=$1 dest=$2 mode=$3
    if [ -f "$dest" ] && cmp -s "$src" "$dest"; then
        chmod "$mode" "$dest"
        say "unchanged ${dest#"$ROOT"}"
        return
    fi
    local verb=installed
    [ -e "$dest" ] && verb=updated
    mkdir -p "$(dirname "$dest")"
    install -m "$mode" "$src" "$dest.tmp.$$"
    mv -f "$dest.tmp.$$" "$dest"
    say "$verb ${dest#"$ROOT"}"
}

recorded_sha() {  # DEST: the checksum this script last installed there, if any
    [ -f "$RECORD" ] || return 0
    awk -v p="${1#"$ROOT"}" '$2 == p {print $1}' "$RECORD" | tail -n 1
}

record_sha() {  # DEST SHA
    local path=${1#"$ROOT"}
    mkdir -p "$(dirname "$RECORD")"
    touch "$RECORD"
    { awk -v p="$path" '$2 != p' "$RECORD"; echo "$2  $path"; } >"$RECORD.tmp.$$"
    mv -f "$RECORD.tmp.$$" "$RECORD"
}

# A config the operator may edit: installed when absent, updated only while unedited.
install_config() {  # SRC DEST
    local src=$1 dest=$2 new
    new=$(sha "$src")
    if [ ! -e "$dest" ]; then
        mkdir -p "$(dirname "$dest")"
        install -m 0640 "$src" "$dest"
        record_sha "$dest" "$new"
        say "installed ${dest#"$ROOT"}"
        return
    fi
    local have last
    have=$(sha "$dest")
    last=$(recorded_sha "$dest")
    if [ "$have" = "$new" ]; then
        [ "$last" = "$new" ] || record_sha "$dest" "$new"
        say "unchanged ${dest#"$ROOT"}"
    elif [ -n "$last" ] && [ "$have" = "$last" ]; then  # ours, unedited: take the new default
        install -m 0640 "$src" "$dest.tmp.$$"
        mv -f "$dest.tmp.$$" "$dest"
        record_sha "$dest" "$new"
        say "updated ${dest#"$ROOT"}"
    elif [ "$last" = "$new" ]; then  # edited, and our default is the same as before
        say "kept your edited ${dest#"$ROOT"}"
    elif [ -f "$dest.dist" ] && cmp -s "$src" "$dest.dist"; then
        say "kept your edited ${dest#"$ROOT"} (the new default is in ${dest#"$ROOT"}.dist)"
    else  # edited, and the default changed: offer it beside the operator's file
        install -m 0640 "$src" "$dest.dist"
        say "kept your edited ${dest#"$ROOT"}; the new default is ${dest#"$ROOT"}.dist"
    fi
}

# 1. The system user, in the device groups (plugdev, video: see 99-topseg.rules).
if [ -n "$ROOT" ]; then
    say "skipped the topseg user (--root)"
else
    for group in plugdev video; do
        if ! getent group "$group" >/dev/null; then
            groupadd --system "$group"
            say "created group $group"
        fi
    done
    if getent passwd topseg >/dev/null; then
        missing=()
        for group in plugdev video; do
            id -nG topseg | tr ' ' '\n' | grep -qx "$group" || missing+=("$group")
        done
        if [ ${#missing[@]} -gt 0 ]; then
            usermod -a -G "$(IFS=,; echo "${missing[*]}")" topseg
            say "added user topseg to ${missing[*]}"
        else
            say "unchanged user topseg (groups plugdev, video)"
        fi
    else
        useradd --system --user-group --home-dir /var/lib/topseg --no-create-home \
            --shell /usr/sbin/nologin --groups plugdev,video --comment "topseg services" topseg
        say "created user topseg (groups plugdev, video)"
    fi
fi

# 2. topseg in its own venv. A stamp of what was installed makes a rerun a no-op.
VENV=$OPT/venv
if [ "$EXTRAS" = auto ]; then
    EXTRAS=""
    [ -f /usr/include/libfreenect/libfreenect.h ] && EXTRAS=kinect
    compgen -G "/usr/lib/*/libOpenNI2.so*" >/dev/null && EXTRAS=${EXTRAS:+$EXTRAS,}openni2
fi
case ",$EXTRAS," in
    *,cell,*) ;;
    *) EXTRAS=cell${EXTRAS:+,$EXTRAS} ;;
esac
if [ -d "$SOURCE" ]; then
    [ -f "$SOURCE/pyproject.toml" ] || die "$SOURCE has no pyproject.toml"
    if git -C "$SOURCE" rev-parse --git-dir >/dev/null 2>&1; then
        digest=$(cd "$SOURCE" && git ls-files -z --cached --others --exclude-standard \
            | sort -z | xargs -0 sha256sum 2>/dev/null | sha256sum | cut -d' ' -f1) || true
    else
        digest=$(cd "$SOURCE" && find . -path ./.venv -prune -o -type f -print0 \
            | sort -z | xargs -0 sha256sum 2>/dev/null | sha256sum | cut -d' ' -f1) || true
    fi
    [ -n "$digest" ] || die "cannot read $SOURCE"
    spec=$SOURCE${EXTRAS:+[$EXTRAS]}
elif [ -f "$SOURCE" ]; then
    digest=$(sha "$SOURCE")
    spec=$SOURCE${EXTRAS:+[$EXTRAS]}
else
    die "--source $SOURCE does not exist"
fi
stamp="source=$digest extras=$EXTRAS pip-args=$PIP_ARGS"
if [ -x "$VENV/bin/topseg" ] && [ "$(cat "$VENV/.topseg-install" 2>/dev/null)" = "$stamp" ]; then
    say "unchanged ${VENV#"$ROOT"} ($("$VENV/bin/topseg" --version))"
else
    if [ ! -x "$VENV/bin/python" ]; then
        "$PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 11))' \
            || die "$PYTHON is older than Python 3.11 (use --python)"
        mkdir -p "$OPT"
        if [ "$VENV_PIP" = 1 ]; then
            "$PYTHON" -m venv "$VENV"
        else
            "$PYTHON" -m venv --without-pip "$VENV"
        fi
        say "created ${VENV#"$ROOT"} ($("$VENV/bin/python" --version))"
    fi
    if [ "$VENV_PIP" = 1 ]; then
        pip=("$VENV/bin/python" -m pip)
    else
        pip=("$PYTHON" -m pip --python "$VENV/bin/python")
    fi
    pip+=(install -q --disable-pip-version-check --root-user-action=ignore)
    # shellcheck disable=SC2086  # PIP_ARGS is a list of arguments
    if [ -d "$SOURCE" ] && [[ " $PIP_ARGS " != *" --no-index "* ]]; then
        "${pip[@]}" --upgrade pip "setuptools>=77" wheel $PIP_ARGS
    fi
    # topseg itself even when its version did not change, then its dependencies (unless
    # the pip arguments say --no-deps).
    # shellcheck disable=SC2086
    "${pip[@]}" --force-reinstall --no-deps $PIP_ARGS "$spec"
    # shellcheck disable=SC2086
    "${pip[@]}" $PIP_ARGS "$spec"
    echo "$stamp" >"$VENV/.topseg-install"
    say "installed topseg into ${VENV#"$ROOT"} ($("$VENV/bin/topseg" --version)${EXTRAS:+, extras $EXTRAS})"
fi

# 3. Data and docs the configs and units point at.
install_file "$CHECKOUT/models/default.npz" "$OPT/models/default.npz" 0644
install_file "$CHECKOUT/recordings/demo.mcap" "$OPT/recordings/demo.mcap" 0644
for doc in howto/deploy.md howto/ros2.md howto/safety.md security.md; do
    [ -f "$CHECKOUT/docs/$doc" ] && install_file "$CHECKOUT/docs/$doc" "$OPT/docs/$doc" 0644
done

# 4. systemd units and udev rules (package files: operators override with drop-ins).
for unit in "$CHECKOUT"/deploy/systemd/*.service; do
    install_file "$unit" "$ROOT/etc/systemd/system/$(basename "$unit")" 0644
done
install_file "$CHECKOUT/deploy/99-topseg.rules" "$ROOT/etc/udev/rules.d/99-topseg.rules" 0644

# 5. Configs: /etc/topseg readable by the topseg group only (they may name keys and certs).
mkdir -p "$ETC/zenoh"
for conf in "$CHECKOUT"/deploy/config/*.toml; do
    install_config "$conf" "$ETC/$(basename "$conf")"
done
for conf in "$CHECKOUT"/deploy/zenoh/*.json5 "$CHECKOUT"/deploy/zenoh/README.md; do
    [ -f "$conf" ] && install_config "$conf" "$ETC/zenoh/$(basename "$conf")"
done
chmod 0750 "$ETC" "$ETC/zenoh"
if [ -z "$ROOT" ]; then
    chgrp -R topseg "$ETC"
fi

# 6. numba's kernels compiled into the services' cache, as the topseg user, so that a worker's
#    first start takes seconds instead of minutes. A failure is a warning: the worker would
#    compile them itself.
CACHE=/var/cache/topseg
if [ "$COMPILE" = 0 ]; then
    say "skipped compiling numba's kernels (--no-compile)"
elif [ -n "$ROOT" ]; then
    say "skipped compiling numba's kernels (--root)"
else
    install -d -o topseg -g topseg -m 0750 "$CACHE" "$CACHE/numba"
    log=$(mktemp)
    if runuser -u topseg -- env HOME="$CACHE" NUMBA_CACHE_DIR="$CACHE/numba" \
        "$VENV/bin/topseg" -q compile >"$log" 2>&1 </dev/null; then
        say "compiled numba's kernels into $CACHE/numba ($(tail -n 1 "$log"))"
    else
        say "warning: could not compile numba's kernels into $CACHE/numba (the worker will" \
            "on its first start): $(grep -v '^ ' "$log" | tail -n 1)"
    fi
    rm -f "$log"
fi

# 7. Tell systemd and udev, where they run.
if [ -z "$ROOT" ] && [ "$SYSTEMCTL" = 1 ]; then
    if command -v systemctl >/dev/null && [ -d /run/systemd/system ]; then
        systemctl daemon-reload
        say "ran systemctl daemon-reload"
    else
        say "skipped systemctl daemon-reload (systemd is not running)"
    fi
    if command -v udevadm >/dev/null && udevadm control --reload 2>/dev/null; then
        say "ran udevadm control --reload (replug the sensors)"
    else
        say "skipped udevadm control --reload (udev is not running)"
    fi
else
    say "skipped systemctl daemon-reload and udevadm control --reload"
fi
say "done; next: edit /etc/topseg/<camera>.toml, then" \
    "systemctl enable --now topseg-driver@<camera> topseg-worker@<camera> (docs/howto/deploy.md)"
