#!/usr/bin/env bash
# A private certificate authority and one certificate per box, for TLS / mTLS between overgrid boxes.
#
#   deploy/make-certs.sh DIR ROUTER_NAME [CLIENT_NAME ...]
#
# DIR gets ca.pem/ca-key.pem, then NAME.pem/NAME-key.pem for the router (its DNS name or IP goes in
# the certificate: clients check it) and for each client (its name is the certificate's common name,
# which the router's access-control subjects can match). Keep ca-key.pem off the boxes.
set -euo pipefail
if [ $# -lt 2 ]; then
  echo "usage: $0 DIR ROUTER_NAME [CLIENT_NAME ...]" >&2
  exit 2
fi
dir=$1
router=$2
shift 2
days=${OVERGRID_CERT_DAYS:-825}
fail() {
  echo "make-certs: $*" >&2
  exit 2
}
[[ $days =~ ^[0-9]+$ ]] || fail "OVERGRID_CERT_DAYS must be a whole number of days, not '$days'"
for name in "$router" "$@"; do # names become file names and certificate names
  [[ $name =~ ^[A-Za-z0-9.:_-]+$ ]] || fail "'$name' is no host name or address (letters, digits, . : _ -)"
done
mkdir -p "$dir"
cd "$dir"

run() { # openssl's own words only when it fails
  local out
  if ! out=$(openssl "$@" 2>&1); then
    echo "make-certs: openssl $1 failed: $out" >&2
    exit 1
  fi
}

if [ ! -f ca.pem ]; then
  run req -x509 -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -days "$days" \
    -keyout ca-key.pem -out ca.pem -subj "/CN=overgrid private CA" \
    -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign"
  echo "made ca.pem"
fi

issue() { # NAME SAN
  local name=$1 san=$2
  run req -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -keyout "$name-key.pem" \
    -out "$name.csr" -subj "/CN=$name"
  run x509 -req -in "$name.csr" -CA ca.pem -CAkey ca-key.pem -CAcreateserial -days "$days" \
    -out "$name.pem" -extfile <(printf '%s\n' \
      "subjectAltName=$san" \
      "basicConstraints=CA:FALSE" \
      "keyUsage=critical,digitalSignature,keyEncipherment" \
      "extendedKeyUsage=serverAuth,clientAuth")
  rm -f "$name.csr"
  chmod 600 "$name-key.pem"
  echo "made $name.pem"
}

if [[ $router =~ ^[0-9.]+$ || $router == *:* ]]; then # an IPv4 or IPv6 address
  issue "$router" "IP:$router"
else
  issue "$router" "DNS:$router"
fi
for client in "$@"; do
  issue "$client" "DNS:$client"
done
