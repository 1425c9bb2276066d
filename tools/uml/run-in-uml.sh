#!/bin/bash
# Run a command inside user-mode Linux, on a real kernel with CAN and vcan0/vcan1 up.
#
#   tools/uml/run-in-uml.sh [--timeout SECONDS] [--mem SIZE] [--job DIR] -- COMMAND [ARG...]
#
# The guest's root filesystem is the host's own (hostfs), so COMMAND sees this checkout and its
# .venv; it runs as root in the current directory. Prints the command's output and exits with its
# status. Exit 124: UML did not finish in time; 125: UML or the guest's CAN setup failed
# (the console log tells why); 127: no user-mode Linux here (apt-get install user-mode-linux).
set -u
here=$(cd "$(dirname "$0")" && pwd)
timeout_s=60
mem=384M
job=""
while [ $# -gt 0 ]; do
  case "$1" in
    --timeout) timeout_s=$2; shift 2 ;;
    --mem) mem=$2; shift 2 ;;
    --job) job=$2; shift 2 ;;
    --) shift; break ;;
    *) break ;;
  esac
done
[ $# -gt 0 ] || { echo "usage: $0 [--timeout S] [--mem SIZE] [--job DIR] -- COMMAND..." >&2; exit 2; }

kernel=/usr/bin/linux.uml
[ -x "$kernel" ] || { echo "run-in-uml: $kernel missing (apt-get install user-mode-linux)" >&2; exit 127; }
modules=$(ls -d /usr/lib/uml/modules/*/ 2>/dev/null | sort -V | tail -n 1)
[ -n "$modules" ] || { echo "run-in-uml: no modules under /usr/lib/uml/modules" >&2; exit 127; }

if [ -z "$job" ]; then job=$(mktemp -d /tmp/uml-job.XXXXXX); else mkdir -p "$job"; fi
job=$(cd "$job" && pwd)
rm -f "$job/status" "$job/output"
{ printf 'cd %q || exit 126\n' "$PWD"; printf '%q ' "$@"; printf '\n'; } > "$job/command"

# UML maps its memory from a file under TMPDIR, which must allow exec; /dev/shm (tmpfs) does,
# where /tmp may be mounted noexec.
if [ -d /dev/shm ] && ! findmnt -n -o OPTIONS --target /dev/shm 2>/dev/null | grep -qw noexec; then
  export TMPDIR=/dev/shm
fi
# Each boot gets its own umid directory so parallel boots do not collide; stdin from /dev/null
# so UML leaves the terminal alone; the console goes to a log for when setup fails.
timeout --kill-after=5 "$timeout_s" "$kernel" \
  mem="$mem" root=/dev/root rootfstype=hostfs rootflags=/ rw \
  init="$here/init.sh" uml_dir="$job" umid=uml con=null con0=null,fd:1 \
  uml_job="$job" uml_modules="${modules%/}" \
  < /dev/null > "$job/console.log" 2>&1
uml_rc=$?

[ -f "$job/output" ] && cat "$job/output"
if [ -f "$job/status" ]; then
  exit "$(cat "$job/status")"
fi
if [ $uml_rc -eq 124 ] || [ $uml_rc -eq 137 ]; then
  echo "run-in-uml: user-mode Linux did not finish within ${timeout_s}s (console: $job/console.log)" >&2
  exit 124
fi
echo "run-in-uml: user-mode Linux exited ($uml_rc) without a result; console log follows" >&2
tail -n 30 "$job/console.log" >&2
exit 125
