#!/usr/bin/env bash
# Issue the client certificates of ONE run, signed by the CA that deploy/tls/make-certs.sh made
# (or your site's CA, as ca.crt + ca.key in OUT_DIR). Their common names name the run, and
# the router's access control generated for that run (`minority deploy acl --run RUN`,
# protocol/acl.py) lets them act in that run only: a rank certificate of run A cannot put
# chunks into run B, hold B's rank tokens or read B's spec.
#
#   deploy/tls/make-run-certs.sh OUT_DIR RUN [ROLE ...]
#
# OUT_DIR   where ca.crt and ca.key are, and where to write (e.g. deploy/tls)
# RUN       the run id, as in minority/RUN/... (1-64 characters of A-Z a-z 0-9 _ . -, not
#           starting with . or -)
# ROLE      rank (default), server, viewer, oracle; one certificate each:
#             ROLE.RUN.crt ROLE.RUN.key    CN minority-ROLE.RUN, e.g. rank.column.crt with
#                                          CN minority-rank.column
# Keys are PKCS#8 PEM (P-256), mode 600; certificates valid DAYS days (default 365). Running
# it again renews them. Point a copy of deploy/zenoh/rank.json5 (server, viewer, oracle.json5)
# at them, e.g.
#   sed 's#deploy/tls/rank\.#deploy/tls/rank.column.#' deploy/zenoh/rank.json5 > rank-column.json5
set -euo pipefail

if [ "$#" -lt 2 ]; then
    echo "usage: $0 OUT_DIR RUN [rank|server|viewer|oracle ...]" >&2
    exit 2
fi
out="$1"
run="$2"
shift 2
roles=("$@")
if [ "${#roles[@]}" -eq 0 ]; then roles=(rank); fi
days="${DAYS:-365}"

# the run ids protocol/keys.py accepts (protocol/check.py NAME_RE): one key-expression chunk
if ! [[ "$run" =~ ^[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}$ ]]; then
    echo "make-run-certs.sh: run id must be 1-64 characters of A-Z a-z 0-9 _ . - not starting with . or -, got '$run'" >&2
    exit 2
fi
for role in "${roles[@]}"; do
    case "$role" in
        rank|server|viewer|oracle) ;;
        *) echo "make-run-certs.sh: ROLE must be rank, server, viewer or oracle, not '$role'" >&2; exit 2 ;;
    esac
done
command -v openssl >/dev/null || { echo "make-run-certs.sh: openssl not found" >&2; exit 1; }
if [ ! -s "$out/ca.crt" ] || [ ! -s "$out/ca.key" ]; then
    echo "make-run-certs.sh: no CA in $out (ca.crt, ca.key): run deploy/tls/make-certs.sh $out first" >&2
    exit 1
fi
umask 077

for role in "${roles[@]}"; do
    name="$role.$run"
    cn="minority-$role.$run"     # protocol/acl.py identity(role, run)
    ext="$(mktemp)"
    {
        echo "basicConstraints=critical,CA:FALSE"
        echo "keyUsage=critical,digitalSignature,keyEncipherment"
        echo "extendedKeyUsage=clientAuth"
    } > "$ext"
    openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$out/$name.key" 2>/dev/null
    openssl req -new -key "$out/$name.key" -subj "/O=minority/CN=$cn" -out "$out/$name.csr"
    openssl x509 -req -in "$out/$name.csr" -CA "$out/ca.crt" -CAkey "$out/ca.key" \
        -CAcreateserial -sha256 -days "$days" -extfile "$ext" -out "$out/$name.crt" 2>/dev/null
    rm -f "$out/$name.csr" "$ext"
    chmod 600 "$out/$name.key"
    chmod 644 "$out/$name.crt"
    openssl verify -CAfile "$out/ca.crt" "$out/$name.crt" >/dev/null
    echo "make-run-certs.sh: $out/$name.crt (CN $cn)"
done
