#!/usr/bin/env bash
# Generate the certificates of a gridslam deployment (docs/security.md):
#
#   deploy/make-certs.sh OUTDIR [ROUTER_NAME ...]
#
# OUTDIR receives a private certificate authority (ca.pem, ca.key) and, signed by it, one
# certificate and key per role: router.pem/.key for the Zenoh router(s), and for the clients
# source, egomotion, gridcells, loopclosure, expmap, viewer (the pipeline services), fleetmap
# (the fleet map over several robots' maps), operator (`gridslam health`, `gridslam echo`) and
# observer (an outside client that may only read poses and the maps). The common name of each client certificate is `gridslam-<role>`; the
# router's access control (deploy/acl/router.json5) grants rights by that name.
#
# The router certificate names `router` (its compose service name), `localhost` and
# 127.0.0.1; give every other name or address under which clients reach a router as
# ROUTER_NAME arguments (DNS names or IPv4/IPv6 addresses), e.g. `router-a.lab 10.0.0.5`.
# Environment: DAYS (validity, default 825), ROLES (client roles, space separated).
set -euo pipefail

if [[ $# -lt 1 || "$1" == -h || "$1" == --help ]]; then
    sed -n '2,16p' "$0" | sed 's/^# \{0,1\}//'
    exit 2
fi
command -v openssl >/dev/null || { echo "make-certs.sh: openssl not found (apt-get install openssl)" >&2; exit 1; }

out=$1; shift
days=${DAYS:-825}
roles=${ROLES:-"source egomotion gridcells loopclosure expmap viewer fleetmap operator observer"}
mkdir -p "$out"
umask 077   # private keys readable by their owner only

# EC P-256 keys in PKCS#8 PEM: accepted by rustls, which Zenoh uses for TLS.
newkey() { openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null; }

# sign NAME CN EXTENSIONS: NAME.pem signed by the CA, for the key NAME.key.
sign() {
    local name=$1 cn=$2 ext=$3
    newkey "$out/$name.key"
    openssl req -new -key "$out/$name.key" -subj "/O=gridslam/CN=$cn" -out "$out/$name.csr" 2>/dev/null
    printf '%s\n' "$ext" > "$out/$name.ext"
    openssl x509 -req -in "$out/$name.csr" -CA "$out/ca.pem" -CAkey "$out/ca.key" -CAcreateserial \
        -days "$days" -sha256 -extfile "$out/$name.ext" -out "$out/$name.pem" 2>/dev/null
    rm -f "$out/$name.csr" "$out/$name.ext"
}

if [[ ! -f "$out/ca.pem" || ! -f "$out/ca.key" ]]; then
    newkey "$out/ca.key"
    openssl req -x509 -new -key "$out/ca.key" -subj "/O=gridslam/CN=gridslam-ca" -days "$days" -sha256 \
        -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" \
        -out "$out/ca.pem" 2>/dev/null
fi

# Subject alternative names of the router: Zenoh checks the name a client connects to against
# these (transport/link/tls/verify_name_on_connect), never the common name.
sans="DNS:router,DNS:localhost,IP:127.0.0.1,IP:::1"
for name in "$@"; do
    if [[ $name =~ ^[0-9.]+$ || $name == *:* ]]; then sans+=",IP:$name"; else sans+=",DNS:$name"; fi
done
# A router both accepts clients and connects to other routers (multi-machine), so it
# authenticates as a server and as a client.
sign router gridslam-router "basicConstraints=critical,CA:FALSE
keyUsage=critical,digitalSignature
extendedKeyUsage=serverAuth,clientAuth
subjectAltName=$sans"

for role in $roles; do
    sign "$role" "gridslam-$role" "basicConstraints=critical,CA:FALSE
keyUsage=critical,digitalSignature
extendedKeyUsage=clientAuth
subjectAltName=DNS:gridslam-$role"
done
chmod 644 "$out"/*.pem
echo "certificates for router and $roles in $out (CA: $out/ca.pem; keep $out/ca.key offline)"
