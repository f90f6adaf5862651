#!/usr/bin/python3
"""BlueZ without radios, for tests/it/bluez.rs: a private system bus with
python-dbusmock's `bluez5` template on it, driven line by line from stdin.

Starts its own dbus-daemon (own config, a socket in a temporary directory),
prints `address <bus address>` once org.bluez is on it, then answers each
command with one line, `ok ...` or `error ...`:

  adapter-add NAME                      add adapter NAME (e.g. hci0)
  adapter-remove NAME                   remove it and its devices (an unplug)
  adapter-power NAME on|off             power it on or off
  beacon NAME ADDR UUID MAJOR MINOR POWER RSSI
                                        a device on NAME that advertises an
                                        iBeacon frame, announced as BlueZ does
                                        (InterfacesAdded with ManufacturerData
                                        and RSSI)
  rssi ADDR RSSI                        the RSSI ADDR's next adverts report
  adverts PERIOD_MS                     every PERIOD_MS, each beacon sends an
                                        advert (PropertiesChanged of RSSI, as
                                        BlueZ reports duplicates); 0 stops
  calls NAME METHOD                     how often METHOD was called on NAME
  connections PID                       how many bus connections process PID has
  quit

What the template cannot carry and this script adds through the mock's
generic org.freedesktop.DBus.Mock interface: the template's AddDevice
declares ManufacturerData with the wrong D-Bus type (an array of a{qv}, not
a{qv}) and fixes it empty, so beacons are built here with AddObject and
announced with EmitSignal; adverts are UpdateProperties calls.

Exits, stopping the bus and the mock, on `quit`, end of input or SIGTERM.
"""

import ctypes
import os
import select
import signal
import struct
import subprocess
import sys
import tempfile
import time
import uuid

import dbus

BLUEZ = "org.bluez"
MOCK_IFACE = "org.freedesktop.DBus.Mock"
BLUEZ_MOCK_IFACE = "org.bluez.Mock"
DEVICE_IFACE = "org.bluez.Device1"
OBJECT_MANAGER_IFACE = "org.freedesktop.DBus.ObjectManager"
APPLE = 0x004C

BUS_CONFIG = """<!DOCTYPE busconfig PUBLIC "-//freedesktop//DTD D-Bus Bus Configuration 1.0//EN"
 "http://www.freedesktop.org/standards/dbus/1.0/busconfig.dtd">
<busconfig>
  <type>system</type>
  <listen>unix:path={socket}</listen>
  <auth>EXTERNAL</auth>
  <policy context="default">
    <allow user="*"/>
    <allow own="*"/>
    <allow send_destination="*"/>
    <allow receive_sender="*"/>
  </policy>
</busconfig>
"""


def die_with_parent():
    """Children get SIGTERM when this script dies, however it dies."""
    libc = ctypes.CDLL(None, use_errno=True)
    PR_SET_PDEATHSIG = 1
    libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


def device_path(adapter, address):
    return f"/org/bluez/{adapter}/dev_{address.replace(':', '_').upper()}"


def ibeacon_payload(proximity_uuid, major, minor, power):
    """What follows Apple's company id in an iBeacon advert."""
    return bytes([0x02, 0x15]) + uuid.UUID(proximity_uuid).bytes + struct.pack(">HHb", major, minor, power)


class Mock:
    def __init__(self, workdir):
        socket = os.path.join(workdir, "system_bus_socket")
        config = os.path.join(workdir, "bus.conf")
        with open(config, "w") as f:
            f.write(BUS_CONFIG.format(socket=socket))
        self.children = []
        bus = subprocess.Popen(
            ["dbus-daemon", f"--config-file={config}", "--nofork", "--nosyslog", "--print-address"],
            stdout=subprocess.PIPE, preexec_fn=die_with_parent, text=True)
        self.children.append(bus)
        self.address = bus.stdout.readline().strip()
        if not self.address:
            raise SystemExit("dbus-daemon did not start")
        env = dict(os.environ, DBUS_SYSTEM_BUS_ADDRESS=self.address)
        self.children.append(subprocess.Popen(
            [sys.executable, "-m", "dbusmock", "--system", "--template", "bluez5"],
            env=env, stdout=subprocess.DEVNULL, preexec_fn=die_with_parent))
        self.bus = dbus.bus.BusConnection(self.address)
        deadline = time.monotonic() + 20
        while not self.bus.name_has_owner(BLUEZ):
            if time.monotonic() > deadline or self.children[-1].poll() is not None:
                raise SystemExit("the bluez5 mock did not come up")
            time.sleep(0.05)
        root = self.bus.get_object(BLUEZ, "/")
        self.bluez = dbus.Interface(root, BLUEZ_MOCK_IFACE)
        self.root = dbus.Interface(root, MOCK_IFACE)
        # address -> (object path, rssi)
        self.beacons = {}
        self.advert_period = 0.0

    def mock_of(self, path):
        return dbus.Interface(self.bus.get_object(BLUEZ, path), MOCK_IFACE)

    def adapter_add(self, name):
        return self.bluez.AddAdapter(name, "gangway-test")

    def adapter_remove(self, name):
        self.bluez.RemoveAdapterWithDevices(name)
        prefix = f"/org/bluez/{name}/"
        self.beacons = {a: b for a, b in self.beacons.items() if not b[0].startswith(prefix)}

    def adapter_power(self, name, state):
        powered = dbus.Boolean(state == "on", variant_level=1)
        self.mock_of(f"/org/bluez/{name}").UpdateProperties("org.bluez.Adapter1", {"Powered": powered})

    def beacon(self, adapter, address, proximity_uuid, major, minor, power, rssi):
        path = device_path(adapter, address)
        payload = ibeacon_payload(proximity_uuid, int(major), int(minor), int(power))
        manufacturer_data = dbus.Dictionary(
            {dbus.UInt16(APPLE): dbus.Array(payload, signature="y")}, signature="qv", variant_level=1)
        adapter_path = f"/org/bluez/{adapter}"
        properties = {
            "Address": dbus.String(address, variant_level=1),
            "AddressType": dbus.String("random", variant_level=1),
            "Alias": dbus.String(address.replace(":", "-"), variant_level=1),
            "Paired": dbus.Boolean(False, variant_level=1),
            "Bonded": dbus.Boolean(False, variant_level=1),
            "Trusted": dbus.Boolean(False, variant_level=1),
            "Blocked": dbus.Boolean(False, variant_level=1),
            "LegacyPairing": dbus.Boolean(False, variant_level=1),
            "Connected": dbus.Boolean(False, variant_level=1),
            "ServicesResolved": dbus.Boolean(False, variant_level=1),
            "UUIDs": dbus.Array([], signature="s", variant_level=1),
            "Adapter": dbus.ObjectPath(adapter_path, variant_level=1),
            "RSSI": dbus.Int16(int(rssi), variant_level=1),
            "ManufacturerData": manufacturer_data,
        }
        self.root.AddObject(path, DEVICE_IFACE, properties, [])
        self.root.EmitSignal(OBJECT_MANAGER_IFACE, "InterfacesAdded", "oa{sa{sv}}",
                             [dbus.ObjectPath(path), {DEVICE_IFACE: properties}])
        self.beacons[address] = (path, int(rssi))
        return path

    def rssi(self, address, rssi):
        path, _ = self.beacons[address]
        self.beacons[address] = (path, int(rssi))

    def advertise(self):
        for path, rssi in self.beacons.values():
            self.mock_of(path).UpdateProperties(DEVICE_IFACE, {"RSSI": dbus.Int16(rssi, variant_level=1)})

    def calls(self, adapter, method):
        return len(self.mock_of(f"/org/bluez/{adapter}").GetMethodCalls(method))

    def connections(self, pid):
        daemon = dbus.Interface(self.bus.get_object("org.freedesktop.DBus", "/org/freedesktop/DBus"),
                                "org.freedesktop.DBus")
        owners = [n for n in daemon.ListNames() if n.startswith(":")]
        return sum(1 for n in owners if daemon.GetConnectionUnixProcessID(n) == int(pid))

    def command(self, words):
        verb, args = words[0], words[1:]
        if verb == "adapter-add":
            return self.adapter_add(*args)
        if verb == "adapter-remove":
            return self.adapter_remove(*args)
        if verb == "adapter-power":
            return self.adapter_power(*args)
        if verb == "beacon":
            return self.beacon(*args)
        if verb == "rssi":
            return self.rssi(*args)
        if verb == "adverts":
            self.advert_period = int(args[0]) / 1000.0
            return None
        if verb == "connections":
            return self.connections(*args)
        if verb == "calls":
            return self.calls(*args)
        raise ValueError(f"unknown command {verb!r}")

    def stop(self):
        for child in reversed(self.children):
            child.terminate()
        for child in self.children:
            try:
                child.wait(timeout=5)
            except subprocess.TimeoutExpired:
                child.kill()


def main():
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    with tempfile.TemporaryDirectory(prefix="gangway-bluez-") as workdir:
        mock = Mock(workdir)
        try:
            print("address", mock.address, flush=True)
            next_advert = time.monotonic()
            pending = b""
            while True:
                if b"\n" not in pending:
                    timeout = None
                    if mock.advert_period > 0:
                        timeout = max(0.0, next_advert - time.monotonic())
                    ready, _, _ = select.select([0], [], [], timeout)
                    if not ready:
                        mock.advertise()
                        next_advert += mock.advert_period
                        continue
                    chunk = os.read(0, 4096)
                    if not chunk:
                        return
                    pending += chunk
                    continue
                line, pending = pending.split(b"\n", 1)
                line = line.decode()
                if line.strip() == "quit":
                    return
                if not line.strip():
                    continue
                try:
                    result = mock.command(line.split())
                    print("ok" if result is None else f"ok {result}", flush=True)
                except (dbus.exceptions.DBusException, ValueError, TypeError, KeyError) as e:
                    print(f"error {e}".replace("\n", " "), flush=True)
                if mock.advert_period > 0:
                    next_advert = max(next_advert, time.monotonic())
        finally:
            mock.stop()


if __name__ == "__main__":
    main()
