#!/usr/bin/env bash
# Installs the Debian package on a clean Debian 12 (a minbase debootstrap in
# a scratch folder, deleted afterwards) with apt, as a user would, and runs
# `gangway check` there with no arguments: the package must find its config
# in /etc/gangway and start without warnings on a system that has nothing but
# what it depends on. Usage: scripts/check_deb_clean_debian.sh PACKAGE.deb
set -euo pipefail
deb=$(realpath "$1")
command -v debootstrap >/dev/null 2>&1 || {
  DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends debootstrap >/dev/null
}
root=$(mktemp -d /tmp/gangway-clean-debian.XXXXXX)
trap 'rm -rf "$root"' EXIT
debootstrap --variant=minbase bookworm "$root" http://deb.debian.org/debian >"$root.log" 2>&1 \
  || { tail -20 "$root.log" >&2; exit 1; }
rm -f "$root.log"
cp /etc/resolv.conf "$root/etc/resolv.conf"
cp "$deb" "$root/tmp/gangway.deb"
chroot "$root" /bin/sh -c \
  'DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends /tmp/gangway.deb' >/dev/null
check_log=$(chroot "$root" /bin/sh -c 'cd / && gangway check 2>&1')
echo "$check_log"
if grep -E ' (WARN|ERROR) |No such file' <<<"$check_log"; then
  echo "gangway check on a clean Debian 12 warned (above)" >&2
  exit 1
fi
echo "clean Debian 12: apt installed $(basename "$deb"), gangway check passed with no arguments"
