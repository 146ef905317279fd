#!/bin/sh
# Write deploy/.env from deploy/.env.example with fresh random secrets (FLEET_AUTH_KEY,
# POSTGRES_PASSWORD, S3_SECRET_ACCESS_KEY), readable by its owner only. An existing .env is
# never overwritten: its key signs every token the depot has handed out.
set -eu
cd "$(dirname "$0")"
if [ -e .env ]; then
    echo "make-env.sh: $(pwd)/.env exists: left as it is" >&2
    exit 1
fi
secret() { openssl rand -hex 32; }
umask 077
sed -e "s/^FLEET_AUTH_KEY=\$/FLEET_AUTH_KEY=$(secret)/" \
    -e "s/^POSTGRES_PASSWORD=\$/POSTGRES_PASSWORD=$(secret)/" \
    -e "s/^S3_SECRET_ACCESS_KEY=\$/S3_SECRET_ACCESS_KEY=$(secret)/" \
    .env.example > .env
echo "make-env.sh: wrote $(pwd)/.env (mode 0600)"
