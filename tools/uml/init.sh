#!/bin/bash
# PID 1 inside user-mode Linux (booted by run-in-uml.sh with the host filesystem as root).
# Sets up a kernel with CAN and two vcan interfaces, runs the job's command, leaves its output
# and exit status in the job directory on the host filesystem, and powers the machine off.
# The kernel passes unknown boot parameters of the form name=value to init as environment:
# uml_job (job directory) and uml_modules (module directory) come that way.
export PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin
export HOME=/root LANG=C.UTF-8
job=${uml_job:?}
modules=${uml_modules:?}

power_off() {
  sync
  echo o > /proc/sysrq-trigger   # init must never exit: the kernel would panic instead
  sleep 10
}

setup_failed() {
  echo "uml init: $*" >> "$job/output"
  echo 125 > "$job/status.tmp" && mv "$job/status.tmp" "$job/status"
  power_off
}

mount -t proc proc /proc || setup_failed "mount /proc failed"
mount -t sysfs sysfs /sys || setup_failed "mount /sys failed"
# Private scratch space: the host's /dev/shm and /run must not be written by the guest.
mkdir -p /dev/shm && mount -t tmpfs tmpfs /dev/shm
mount -t tmpfs tmpfs /run

# Dependency order: can-raw and can-gw need can; vcan needs can-dev.
for m in net/can/can.ko net/can/can-raw.ko net/can/can-gw.ko drivers/net/can/dev/can-dev.ko drivers/net/can/vcan.ko; do
  insmod "$modules/kernel/$m" 2>>"$job/output" || setup_failed "insmod $m failed"
done
ip link set lo up || setup_failed "ip link set lo up failed"
for dev in vcan0 vcan1; do
  # mtu 72: CAN FD frames (the authenticated magnetorquer command is one).
  { ip link add dev "$dev" type vcan && ip link set "$dev" mtu 72 && ip link set "$dev" up; } 2>>"$job/output" \
    || setup_failed "creating $dev failed"
done

bash "$job/command" >> "$job/output" 2>&1
echo $? > "$job/status.tmp" && mv "$job/status.tmp" "$job/status"
power_off
