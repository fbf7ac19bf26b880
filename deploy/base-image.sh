#!/bin/sh
# A stand-in for python:3.11-slim where Docker Hub cannot be reached (docs/deploy.md, "Without
# Docker Hub"): Debian bookworm (debootstrap --variant=minbase) with Debian's Python 3.11 and its
# venv module, imported into the local Docker engine as TAG. Needs root, debootstrap and a
# Debian mirror; the downloaded packages are kept in CACHE for the next time.
#
#   deploy/base-image.sh gridslam/python:3.11-bookworm
#   docker-compose build --build-arg BASE_IMAGE=gridslam/python:3.11-bookworm   (or GRIDSLAM_BASE_IMAGE=...)
set -eu
TAG=${1:?usage: $0 TAG (e.g. gridslam/python:3.11-bookworm)}
MIRROR=${MIRROR:-http://deb.debian.org/debian}
CACHE=${CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/gridslam/debootstrap}
mkdir -p "$CACHE"
root=$(mktemp -d)
trap 'rm -rf "$root"' EXIT
debootstrap --variant=minbase --include=python3,python3-venv,ca-certificates --cache-dir="$CACHE" \
    bookworm "$root" "$MIRROR"
# What python:3.11-slim leaves out too: package lists and caches, documentation, translations.
rm -rf "$root"/var/cache/apt/* "$root"/var/lib/apt/lists/* "$root"/usr/share/doc/* "$root"/usr/share/man/* \
    "$root"/usr/share/info/* "$root"/usr/share/locale/*
tar -C "$root" -c . | docker import --change 'ENV LANG=C.UTF-8' --change 'CMD ["python3"]' \
    --message "debootstrap bookworm minbase + python3 (stand-in for python:3.11-slim)" - "$TAG"
