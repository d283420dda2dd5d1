#!/usr/bin/env bash
# Makes Debian's PostgreSQL server programs (initdb, pg_ctl) available for tests/test_tune_postgres.py,
# which starts its own throw-away server on 127.0.0.1 in a temporary folder. Installs nothing when they
# are already there; needs root (apt-get) otherwise. No cluster is created or started here.
set -euo pipefail

if command -v pg_ctl >/dev/null 2>&1 || compgen -G "/usr/lib/postgresql/*/bin/pg_ctl" >/dev/null; then
    echo "ci_postgres: PostgreSQL server programs found"
    exit 0
fi
if [ "$(id -u)" != "0" ]; then
    echo "ci_postgres: PostgreSQL is not installed and this user cannot apt-get install it" >&2
    exit 1
fi
if ! command -v apt-get >/dev/null 2>&1; then
    echo "ci_postgres: PostgreSQL is not installed and apt-get is not available" >&2
    exit 1
fi
# the tests run their own server: keep the package from creating (and starting) the default cluster
mkdir -p /etc/postgresql-common
if ! grep -qs '^create_main_cluster' /etc/postgresql-common/createcluster.conf; then
    echo "create_main_cluster = false" >> /etc/postgresql-common/createcluster.conf
fi
export DEBIAN_FRONTEND=noninteractive
apt-get update -qq
apt-get install -y -qq --no-install-recommends -o Dpkg::Options::=--force-confdef \
    -o Dpkg::Options::=--force-confold postgresql >/dev/null
compgen -G "/usr/lib/postgresql/*/bin/pg_ctl" >/dev/null
echo "ci_postgres: installed $(ls -d /usr/lib/postgresql/*/bin | tail -n 1)"
