"""Tier 1: the simulated drive's SDO server answers CiA 301 requests byte for byte."""

from __future__ import annotations

from can_config import GENERIC_EDS, load_drive_od
from virtual_can.sim.drive import SimulatedDrive
from virtual_can.sim.objects import ObjectStore
from virtual_can.sim.sdo import SdoServer


def server() -> SdoServer:
    return SdoServer(ObjectStore(load_drive_od(GENERIC_EDS, 1)))


def test_expedited_upload_of_device_type() -> None:
    assert server().handle(bytes.fromhex("4000100000000000")) == bytes.fromhex("4300100092010200")


def test_expedited_download_and_read_back() -> None:
    sdo = server()
    assert sdo.handle(bytes.fromhex("2b17100064000000")) == bytes.fromhex("6017100000000000")
    assert sdo.handle(bytes.fromhex("4017100000000000")) == bytes.fromhex("4b17100064000000")


def test_segmented_upload_of_device_name() -> None:
    sdo = server()
    name = b"rovercan generic CiA 402 servo"
    first = sdo.handle(bytes.fromhex("4008100000000000"))
    assert first == bytes.fromhex("41081000") + len(name).to_bytes(4, "little")
    data = b""
    toggle = 0
    while True:
        seg = sdo.handle(bytes([0x60 | toggle << 4]) + bytes(7))
        assert seg is not None and seg[0] >> 4 & 1 == toggle
        n = seg[0] >> 1 & 7
        data += seg[1:8 - n]
        toggle ^= 1
        if seg[0] & 1:
            break
    assert data == name


def test_aborts_carry_the_standard_codes() -> None:
    sdo = server()
    assert sdo.handle(bytes.fromhex("4034120000000000")) == bytes.fromhex("8034120000000206")  # no object
    assert sdo.handle(bytes.fromhex("4018100900000000")) == bytes.fromhex("8018100911000906")  # no subindex
    assert sdo.handle(bytes.fromhex("2b41600000000000")) == bytes.fromhex("8041600002000106")  # read-only
    assert sdo.handle(bytes.fromhex("2317100001000000")) == bytes.fromhex("8017100010000706")  # length


def test_mapping_change_requires_invalid_pdo() -> None:
    sdo = SimulatedDrive(1, load_drive_od(GENERIC_EDS, 1)).sdo
    # clearing RPDO1's mapping while its COB-ID is valid: abort 0x08000022 (device state)
    assert sdo.handle(bytes.fromhex("2f00160000000000")) == bytes.fromhex("8000160022000008")
