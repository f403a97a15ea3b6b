#!/usr/bin/env python3
"""Writes the fuzzers' seed corpus (tests/fuzz/corpus/<target>/seed-*), small valid inputs
that the fuzzers mutate. Regression inputs (crashes once found, now fixed) live beside them as
regression-* files and are not touched.

    .venv/bin/python tests/fuzz/make_seeds.py     # after a build (it imports palpsim's protobuf code)
"""
import gzip
import os
import shutil
import struct
import sys

here = os.path.dirname(os.path.abspath(__file__))
root = os.path.dirname(os.path.dirname(here))
sys.path.insert(0, os.path.join(root, "clients", "python"))
from palpsim.proto import wire as v1  # noqa: E402  (the generated wire messages)


def write(target, name, data):
    d = os.path.join(here, "corpus", target)
    os.makedirs(d, exist_ok=True)
    with open(os.path.join(d, "seed-" + name), "wb") as f:
        f.write(data)


def clear(target):
    d = os.path.join(here, "corpus", target)
    for n in os.listdir(d) if os.path.isdir(d) else []:
        if n.startswith("seed-"):
            os.remove(os.path.join(d, n))


# --- CT headers: the first byte picks the name (fuzz_ct_header.cpp) ---------------------
NII, NII_GZ, NRRD, NHDR, MHA, MHD = range(6)


def nifti_header(nx=4, ny=5, nz=6, spacing=(0.8, 0.8, 2.5), datatype=4, bitpix=16, order="<"):
    """A NIfTI-1 header (352 bytes) with pixdim = spacing and a scaled identity sform."""
    h = bytearray(352)
    struct.pack_into(order + "i", h, 0, 348)
    struct.pack_into(order + "8h", h, 40, 3, nx, ny, nz, 1, 1, 1, 1)
    struct.pack_into(order + "hh", h, 70, datatype, bitpix)
    struct.pack_into(order + "4f", h, 76, 1, *spacing)
    struct.pack_into(order + "ff", h, 108, 352, 1)  # vox_offset, scl_slope
    h[123] = 2  # mm
    struct.pack_into(order + "hh", h, 252, 0, 1)  # qform 0, sform 1
    struct.pack_into(order + "f", h, 280, spacing[0])
    struct.pack_into(order + "f", h, 300, spacing[1])
    struct.pack_into(order + "f", h, 320, spacing[2])
    h[344:348] = b"n+1\0"
    return bytes(h)


def ct_header_seeds():
    clear("ct_header")
    voxels = struct.pack("<%dh" % 120, *range(120))
    write("ct_header", "nii", bytes([NII]) + nifti_header() + voxels)
    write("ct_header", "nii-float", bytes([NII]) + nifti_header(2, 2, 2, datatype=16, bitpix=32) + b"\0" * 32)
    write("ct_header", "nii-big-endian", bytes([NII]) + nifti_header(order=">") + struct.pack(">%dh" % 120, *range(120)))
    write("ct_header", "nii-gz", bytes([NII_GZ]) + gzip.compress(nifti_header() + voxels, mtime=0))
    nrrd = (b"NRRD0004\ntype: short\ndimension: 3\nspace: left-posterior-superior\nsizes: 4 5 6\n"
            b"space directions: (0.8,0,0) (0,0.8,0) (0,0,2.5)\nspace origin: (-10,-20,30)\n"
            b"endian: little\nencoding: raw\n\n")
    write("ct_header", "nrrd", bytes([NRRD]) + nrrd + voxels)
    nhdr = nrrd.replace(b"encoding: raw\n", b"encoding: raw\ndata file: ct.raw\n")
    write("ct_header", "nhdr", bytes([NHDR]) + nhdr)
    gz = nrrd.replace(b"encoding: raw", b"encoding: gzip").replace(b"space origin", b"# a comment\nspace origin")
    write("ct_header", "nrrd-gzip", bytes([NRRD]) + gz + gzip.compress(voxels, mtime=0))
    mha = (b"ObjectType = Image\nNDims = 3\nBinaryData = True\nBinaryDataByteOrderMSB = False\n"
           b"TransformMatrix = 1 0 0 0 1 0 0 0 1\nOffset = -10 -20 30\nElementSpacing = 0.8 0.8 2.5\n"
           b"DimSize = 4 5 6\nElementType = MET_SHORT\nElementDataFile = LOCAL\n")
    write("ct_header", "mha", bytes([MHA]) + mha + voxels)
    write("ct_header", "mhd", bytes([MHD]) + mha.replace(b"= LOCAL", b"= ct.raw"))


# --- scenes --------------------------------------------------------------------------
def scene_seeds():
    clear("scene")
    scenes = os.path.join(root, "config", "scenes")
    for n in sorted(os.listdir(scenes)):
        if n.endswith(".textproto"):
            shutil.copyfile(os.path.join(scenes, n), os.path.join(here, "corpus", "scene", "seed-" + n))
    write("scene", "phantom.textproto", b'name: "p" phantom { voxel_mm: 2.0 }\n')
    write("scene", "ct.textproto",
          b'name: "ct" ct_path: "ct.nii.gz" prep { spacing_mm: 1.5 bone_threshold: 180 }\n'
          b'haptics { stiffness_n_per_mm: 0.3 max_force_n: 3.3 skin_point: "line" }\n'
          b'server { session_timeout_s: 2 max_sessions: 8 }\n')
    write("scene", "render.textproto",
          b'name: "r" phantom {} effects { frames: true bricks: true } '
          b'render { preset: "bone" width: 640 height: 360 max_fps: 15 record_dir: "frames" }\n')


# --- wire: [kind][length, 2 bytes little-endian][payload] (fuzz_wire.cpp) ------------
POSE, CONTROL = 0, 1
DEALER, REQ, SPLIT, EMPTY = 0, 2, 4, 6
NEWEST = 1  # stands for the newest session the input opened


def msg(kind, payload):
    return bytes([kind]) + struct.pack("<H", len(payload)) + payload


def control(**body):
    q = v1.ControlRequest(schema_version=1, request_id=7, **body)
    return q.SerializeToString()


def pose(session=NEWEST, seq=1, tip=(0.0, 0.0, 35.0), **extra):
    q = v1.PoseRequest(schema_version=1, session_id=session, seq=seq, client_time_s=0.001 * seq,
                       tip_mm=v1.Vec3(x=tip[0], y=tip[1], z=tip[2]), **extra)
    return q.SerializeToString()


def wire_seeds():
    clear("wire")
    opened = msg(CONTROL | DEALER, control(open=v1.OpenSession(client_name="fuzz")))
    write("wire", "open-poses-close",
          opened + b"".join(msg(POSE | DEALER, pose(seq=s, tip=(30.0, 30.0, 40.0 - 0.5 * s))) for s in range(1, 6))
          + msg(CONTROL | DEALER, control(close=v1.CloseSession(session_id=NEWEST))))
    write("wire", "patches",
          opened + msg(POSE | DEALER, pose(seq=1, tip=(30.0, 30.0, 36.0), local_model_edge=8,
                                           local_model_period_s=0.05, renders_locally=True)))
    write("wire", "reset-parameter-stats",
          opened + msg(POSE | REQ, pose(seq=1, reset_proxy=True))
          + msg(CONTROL | DEALER, control(reset=v1.ResetSession(session_id=NEWEST)))
          + msg(CONTROL | REQ, control(set_parameter=v1.SetParameter(session_id=NEWEST, name="friction", value=0.1)))
          + msg(CONTROL | DEALER, control(stats=v1.StatsRequest(session_id=NEWEST))))
    write("wire", "info-watch",
          msg(CONTROL | DEALER, control(info=v1.InfoRequest())) + opened
          + msg(CONTROL | DEALER, control(watch=v1.WatchSession(session_id=NEWEST, frames=True, bricks=True))))
    write("wire", "load-scene",
          msg(CONTROL | DEALER, control(load_scene=v1.LoadScene(text='name: "fuzz" phantom { voxel_mm: 2 }'))))
    write("wire", "load-path", msg(CONTROL | REQ, control(load_scene=v1.LoadScene(path="scene.textproto"))))
    write("wire", "frames",
          msg(POSE | SPLIT, pose(seq=3)) + msg(POSE | EMPTY, b"") + msg(CONTROL | EMPTY, b"")
          + msg(CONTROL | SPLIT, control(info=v1.InfoRequest())) + msg(POSE | DEALER, b"\xff\xfe not a pose"))
    write("wire", "bad-poses",
          opened + msg(POSE | DEALER, pose(tip=(float("nan"), 0.0, 0.0)))
          + msg(POSE | DEALER, pose(tip=(1e9, 0.0, 0.0))) + msg(POSE | DEALER, pose(session=12345))
          + msg(POSE | DEALER, pose(local_model_edge=99)))


if __name__ == "__main__":
    ct_header_seeds()
    scene_seeds()
    wire_seeds()
    for t in ("ct_header", "scene", "wire"):
        d = os.path.join(here, "corpus", t)
        print("%s: %d files, %d bytes" % (t, len(os.listdir(d)), sum(os.path.getsize(os.path.join(d, n)) for n in os.listdir(d))))
