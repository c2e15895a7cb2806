#!/usr/bin/env bash
# Make the keys of an l2r deployment: a CA, one certificate per role, random passwords, and each
# role's Zenoh config rendered from deploy/zenoh/<role>.json5.
#
#   deploy/make-secrets.sh [-o OUTDIR] [-m MOUNTED_AT] [-n ROUTER_NAME]... [-d DAYS]
#
#   -o OUTDIR      where to write (default: deploy/secrets, which git ignores)
#   -m MOUNTED_AT  the path at which a process sees its role's directory; the configs point there
#                  (default: /srv/l2r/secrets, where docker-compose.yml mounts it; a {role} in it
#                  becomes the role's name, e.g. -m "$PWD/secrets/{role}" to run on this host)
#   -n NAME        a DNS name or IP address clients use to reach the router; repeat for each
#                  (default: router, localhost, 127.0.0.1). TLS checks it against the certificate.
#   -d DAYS        certificate lifetime (default: 365)
#
# OUTDIR/ca/ holds the CA key: keep it off the hosts. OUTDIR/<role>/ goes to the hosts of that
# role only: ca.pem, cert.pem, key.pem, zenoh.json5 (and users.txt for the router).
# An existing OUTDIR/ca is reused, so certificates made later still verify against it.
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
out="$here/secrets"
mounted_at=/srv/l2r/secrets
days=365
names=()
while getopts "o:m:n:d:h" opt; do
  case $opt in
    o) out="$OPTARG" ;;
    m) mounted_at="$OPTARG" ;;
    n) names+=("$OPTARG") ;;
    d) days="$OPTARG" ;;
    *) sed -n '2,19p' "$0"; exit 2 ;;
  esac
done
[ ${#names[@]} -eq 0 ] && names=(router localhost 127.0.0.1)
command -v openssl >/dev/null || { echo "make-secrets.sh: openssl not found" >&2; exit 1; }

umask 077
mkdir -p "$out/ca"
if [ ! -f "$out/ca/ca.pem" ]; then
  openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -days "$days" \
    -subj "/CN=l2r deployment CA" -keyout "$out/ca/ca.key" -out "$out/ca/ca.pem" 2>/dev/null
fi

san_of() {  # subjectAltName for a list of names: IP:... for addresses, DNS:... otherwise
  local san="" n
  for n in "$@"; do
    if [[ $n =~ ^[0-9.]+$ || $n == *:* ]]; then san+="IP:$n,"; else san+="DNS:$n,"; fi
  done
  echo "${san%,}"
}

users=""
for role in router replay learner actor; do
  dir="$out/$role"
  mkdir -p "$dir"
  if [ "$role" = router ]; then san=$(san_of "${names[@]}"); else san="DNS:$role"; fi
  # The common name is the role: the router's access control matches it (cert_common_names).
  openssl req -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -subj "/CN=$role" \
    -keyout "$dir/key.pem" -out "$dir/cert.csr" 2>/dev/null
  openssl x509 -req -in "$dir/cert.csr" -CA "$out/ca/ca.pem" -CAkey "$out/ca/ca.key" \
    -CAcreateserial -days "$days" -out "$dir/cert.pem" \
    -extfile <(printf 'subjectAltName=%s\nbasicConstraints=CA:FALSE\nkeyUsage=digitalSignature\nextendedKeyUsage=serverAuth,clientAuth\n' "$san") \
    2>/dev/null
  rm "$dir/cert.csr"
  cp "$out/ca/ca.pem" "$dir/ca.pem"
  password=$(openssl rand -hex 16)
  [ "$role" = router ] || users+="$role:$password"$'\n'
  sed -e "s|@SECRETS@|${mounted_at//\{role\}/$role}|g" -e "s|@PASSWORD@|$password|g" \
    "$here/zenoh/$role.json5" > "$dir/zenoh.json5"
done
printf '%s' "$users" > "$out/router/users.txt"
# Containers run as other users than the one running this script: let them read their keys.
chmod -R a+rX "$out"/router "$out"/replay "$out"/learner "$out"/actor
echo "wrote $out/{ca,router,replay,learner,actor} (router names: ${names[*]}; configs point at $mounted_at)"
