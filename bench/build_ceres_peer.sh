#!/bin/sh
# Builds the Ceres Solver peer of `cargo bench --bench solve_session` into OUT (default
# target/bench-data/ceres_multilateration). Optional: needs Debian's libceres-dev
# (`apt-get install libceres-dev`); exits 3 with a reason when it is not installed.
set -eu
here=$(cd "$(dirname "$0")" && pwd)
out=${1:-"$here/../target/bench-data/ceres_multilateration"}
if [ ! -f /usr/include/ceres/ceres.h ]; then
    echo "Ceres Solver headers not found (/usr/include/ceres/ceres.h): apt-get install libceres-dev" >&2
    exit 3
fi
mkdir -p "$(dirname "$out")"
${CXX:-g++} -O3 -march=native -DNDEBUG -std=c++17 -I/usr/include/eigen3 \
    "$here/ceres_multilateration.cc" -o "$out" -lceres -lglog -lgflags -lpthread
echo "$out"
