#!/usr/bin/env bash
# Generate a TEST certificate authority and the certificates that deploy/zenoh/*.json5 name,
# with openssl. For trying TLS and the router's access control, not for production: use
# your site's CA there, keeping the same common names (the router's ACL matches on them).
#
#   deploy/tls/make-certs.sh [OUT_DIR] [ROUTER_HOST ...]
#
# OUT_DIR       where to write (default: the directory of this script, deploy/tls/)
# ROUTER_HOST   names or IP addresses the router is reached at, as written in the clients'
#               tls/HOST:PORT endpoints (zenoh checks the router certificate's names;
#               localhost and 127.0.0.1 are always included)
#
# Writes (keys are PKCS#8 PEM, mode 600; certificates valid DAYS days, default 365):
#   ca.crt ca.key              the test CA (root_ca_certificate in every config)
#   router.crt router.key      zenohd's certificate, CN minority-router, SAN = ROUTER_HOSTs
#   server.crt server.key      the render server's client certificate, CN minority-server
#   rank.crt rank.key          the ranks' client certificate, CN minority-rank
#   viewer.crt viewer.key      a read-only client (minority record), CN minority-viewer
# An existing CA in OUT_DIR is reused, so certificates can be added or renewed later.
set -euo pipefail

out="${1:-$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)}"
if [ "$#" -gt 0 ]; then shift; fi
days="${DAYS:-365}"
command -v openssl >/dev/null || { echo "make-certs.sh: openssl not found" >&2; exit 1; }
mkdir -p "$out"
umask 077

san="DNS:localhost,IP:127.0.0.1"
for host in "$@"; do
    if [[ "$host" =~ ^[0-9.]+$ || "$host" == *:* ]]; then san="$san,IP:$host"; else san="$san,DNS:$host"; fi
done

newkey() {  # a P-256 key in PKCS#8 PEM
    openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null
}

if [ ! -s "$out/ca.key" ] || [ ! -s "$out/ca.crt" ]; then
    newkey "$out/ca.key"
    openssl req -x509 -new -key "$out/ca.key" -sha256 -days "$days" \
        -subj "/O=minority/CN=minority-test-ca" \
        -addext "basicConstraints=critical,CA:TRUE" \
        -addext "keyUsage=critical,keyCertSign,cRLSign" \
        -out "$out/ca.crt"
fi

# leaf NAME COMMON_NAME EXTENDED_KEY_USAGE [SUBJECT_ALT_NAMES]
leaf() {
    local name="$1" cn="$2" eku="$3" alt="${4:-}"
    local ext; ext="$(mktemp)"
    {
        echo "basicConstraints=critical,CA:FALSE"
        echo "keyUsage=critical,digitalSignature,keyEncipherment"
        echo "extendedKeyUsage=$eku"
        if [ -n "$alt" ]; then echo "subjectAltName=$alt"; fi
    } > "$ext"
    newkey "$out/$name.key"
    openssl req -new -key "$out/$name.key" -subj "/O=minority/CN=$cn" -out "$out/$name.csr"
    openssl x509 -req -in "$out/$name.csr" -CA "$out/ca.crt" -CAkey "$out/ca.key" \
        -CAcreateserial -sha256 -days "$days" -extfile "$ext" -out "$out/$name.crt" 2>/dev/null
    rm -f "$out/$name.csr" "$ext"
}

leaf router minority-router serverAuth,clientAuth "$san"
leaf server minority-server clientAuth
leaf rank minority-rank clientAuth
leaf viewer minority-viewer clientAuth
chmod 600 "$out"/*.key
chmod 644 "$out"/*.crt

for name in router server rank viewer; do
    openssl verify -CAfile "$out/ca.crt" "$out/$name.crt" >/dev/null
done
echo "make-certs.sh: test CA and certificates in $out (router names: $san)"
