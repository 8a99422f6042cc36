#!/bin/sh
# Make the certificates of topseg's secure Zenoh configs (deploy/zenoh/secure-*.json5).
#
#   deploy/make-certs.sh [--force] DIR [HOSTNAME ...]
#
# Writes into DIR (created mode 0750):
#   ca.pem, ca-key.pem           a private CA (EC P-256, 10 years); its key signs the rest
#   router.pem, router-key.pem   the router (serverAuth; SAN localhost, 127.0.0.1, ::1 and
#                                every HOSTNAME given, e.g. the cell PC's name and address)
#   driver.pem,  driver-key.pem  client certificates (clientAuth), CN topseg-driver,
#   worker.pem,  worker-key.pem  topseg-worker and topseg-viewer: the secure router's
#   viewer.pem,  viewer-key.pem  access control tells the roles apart by these CNs
# Keys are mode 0600, certificates 0644. Leaf certificates last 825 days.
#
# Idempotent: files that exist are kept and nothing is overwritten. --force reissues the
# router and client certificates (new keys) from the existing CA: that is how to rotate
# them without touching ca.pem on the other machines. To replace the CA itself, remove
# ca.pem and ca-key.pem first (then every machine needs the new ca.pem).
# These are test and small-site certificates. Move ca-key.pem off the cell PCs once done;
# the script asks for it back only when it has a certificate to issue.
set -eu

usage() {
    echo "usage: $0 [--force] DIR [HOSTNAME ...]" >&2
    exit 2
}

FORCE=0
while [ $# -gt 0 ]; do
    case "$1" in
        --force) FORCE=1; shift ;;
        -h|--help) sed -n '2,20p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
        --) shift; break ;;
        -*) echo "$0: unknown option $1" >&2; usage ;;
        *) break ;;
    esac
done
[ $# -ge 1 ] || usage
DIR=$1
shift
command -v openssl >/dev/null || { echo "$0: openssl is not installed" >&2; exit 1; }

umask 077
mkdir -p "$DIR"
chmod 0750 "$DIR"
TMP=$(mktemp -d)
trap 'rm -rf "$TMP"' EXIT

DAYS_CA=3650
DAYS=825
made=""

key() {  # key FILE: a new EC P-256 private key (PKCS#8), mode 0600
    openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null
    chmod 0600 "$1"
}

# 1. The CA: kept if it exists, even with --force. ca-key.pem may be kept elsewhere; it is
#    needed only when a certificate is to be issued.
if [ -f "$DIR/ca.pem" ]; then
    :
elif [ -f "$DIR/ca-key.pem" ]; then
    echo "$0: $DIR has ca-key.pem but no ca.pem; restore ca.pem or remove the key" >&2
    exit 1
else
    key "$TMP/ca-key.pem"
    openssl req -x509 -new -key "$TMP/ca-key.pem" -sha256 -days "$DAYS_CA" \
        -subj "/O=topseg/CN=topseg CA" \
        -addext "basicConstraints=critical,CA:TRUE,pathlen:0" \
        -addext "keyUsage=critical,keyCertSign,cRLSign" \
        -addext "subjectKeyIdentifier=hash" \
        -out "$TMP/ca.pem"
    mv "$TMP/ca-key.pem" "$DIR/ca-key.pem"
    chmod 0644 "$TMP/ca.pem"
    mv "$TMP/ca.pem" "$DIR/ca.pem"
    made="$made ca.pem"
fi

# leaf NAME CN USAGE SAN: NAME.pem and NAME-key.pem signed by the CA
leaf() {
    name=$1 cn=$2 usage=$3 san=$4
    if [ "$FORCE" = 0 ] && [ -f "$DIR/$name.pem" ] && [ -f "$DIR/$name-key.pem" ]; then
        return
    fi
    if [ ! -f "$DIR/ca-key.pem" ]; then
        echo "$0: $DIR/ca-key.pem is needed to issue $name.pem; put it back (it was moved off?)" >&2
        exit 1
    fi
    key "$TMP/$name-key.pem"
    openssl req -new -key "$TMP/$name-key.pem" -subj "/O=topseg/CN=$cn" -out "$TMP/$name.csr"
    cat >"$TMP/$name.ext" <<EOF
basicConstraints=critical,CA:FALSE
keyUsage=critical,digitalSignature
extendedKeyUsage=$usage
subjectAltName=$san
subjectKeyIdentifier=hash
authorityKeyIdentifier=keyid
EOF
    openssl x509 -req -in "$TMP/$name.csr" -CA "$DIR/ca.pem" -CAkey "$DIR/ca-key.pem" \
        -CAcreateserial -CAserial "$TMP/ca.srl" -sha256 -days "$DAYS" \
        -extfile "$TMP/$name.ext" -out "$TMP/$name.pem" 2>/dev/null
    chmod 0644 "$TMP/$name.pem"
    mv "$TMP/$name-key.pem" "$DIR/$name-key.pem"
    mv "$TMP/$name.pem" "$DIR/$name.pem"
    made="$made $name.pem"
}

san="DNS:localhost,IP:127.0.0.1,IP:::1"
for host in "$@"; do
    case "$host" in
        *[!0-9.]*) case "$host" in *:*) san="$san,IP:$host" ;; *) san="$san,DNS:$host" ;; esac ;;
        *) san="$san,IP:$host" ;;
    esac
done
leaf router topseg-router serverAuth "$san"
for role in driver worker viewer; do
    leaf "$role" "topseg-$role" clientAuth "DNS:topseg-$role"
done

if [ -n "$made" ]; then
    echo "made in $DIR:$made"
else
    echo "$DIR already holds every certificate (--force reissues the router and client ones)"
fi
