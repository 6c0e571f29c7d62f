#!/usr/bin/env bash
# Put ONNX Runtime's C/C++ API headers in $1 (default build/ort-include), for building the custom-op library.
#
# The onnxruntime wheel ships no headers. Debian 13 packages them (libonnxruntime-dev, C API 21). This fetches
# that one .deb with apt-get from a private source list (the system's sources and package state untouched)
# and unpacks it with dpkg -x. Where that is not possible, set ORT_INCLUDE_DIR to the include/ folder of an
# ONNX Runtime release archive instead (make kernel ORT_INCLUDE_DIR=...).
set -euo pipefail
dest=${1:-build/ort-include}
if [ -f "$dest/onnxruntime_lite_custom_op.h" ]; then exit 0; fi
command -v apt-get >/dev/null && command -v dpkg >/dev/null || {
  echo "error: apt-get and dpkg are needed to fetch ONNX Runtime's headers; set ORT_INCLUDE_DIR to an ONNX Runtime release's include/ folder" >&2
  exit 2
}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
mkdir -p "$work/sources" "$work/lists/partial" "$work/archives/partial"
mirror=$(grep -h -m1 '^URIs:.*debian/\?$' /etc/apt/sources.list.d/*.sources 2>/dev/null | awk '{print $2}' || true)
cat > "$work/sources/trixie.sources" <<SRC
Types: deb
URIs: ${mirror:-http://deb.debian.org/debian}
Suites: trixie
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg
SRC
apt_opts=(-qq -o Dir::Etc::sourcelist=/dev/null -o "Dir::Etc::sourceparts=$work/sources" -o "Dir::State::Lists=$work/lists"
          -o "Dir::Cache::archives=$work/archives" -o Debug::NoLocking=1 -o APT::Sandbox::User=root)
apt-get "${apt_opts[@]}" update >/dev/null || { echo "error: could not read Debian 13's package index; set ORT_INCLUDE_DIR instead" >&2; exit 2; }
(cd "$work" && apt-get "${apt_opts[@]}" download libonnxruntime-dev >/dev/null) || {
  echo "error: could not download libonnxruntime-dev from Debian 13; set ORT_INCLUDE_DIR instead" >&2; exit 2; }
dpkg -x "$work"/libonnxruntime-dev_*.deb "$work/pkg"
mkdir -p "$dest.tmp"
cp "$work"/pkg/usr/include/onnxruntime/*.h "$dest.tmp/"
rm -rf "$dest" && mv "$dest.tmp" "$dest"
echo "ONNX Runtime headers (Debian 13 libonnxruntime-dev) in $dest"
