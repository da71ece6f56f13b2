#!/usr/bin/env python3
"""Writes the MNI152 T1 template shipped inside nilearn's wheel as a RAW u8 file.

The template (mni_icbm152_t1_tal_nlin_sym_09a_converted.nii.gz, 197x233x189, uint8) is a real
MRI scan. Only the wheel is fetched (pip download --no-deps): no numpy or nibabel is needed,
the NIfTI-1 header is read with struct.
"""
import glob
import gzip
import struct
import subprocess
import sys
import tempfile
import zipfile

out = sys.argv[1] if len(sys.argv) > 1 else "mni152_t1.raw"
with tempfile.TemporaryDirectory() as d:
    subprocess.run([sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "-d", d, "nilearn"], check=True)
    wheel = glob.glob(f"{d}/nilearn-*.whl")[0]
    nii = gzip.decompress(zipfile.ZipFile(wheel).read("nilearn/datasets/data/mni_icbm152_t1_tal_nlin_sym_09a_converted.nii.gz"))
dims = struct.unpack("<8h", nii[40:56])
datatype, bitpix = struct.unpack("<hh", nii[70:74])
vox_offset = int(struct.unpack("<f", nii[108:112])[0])
assert dims[0] == 3 and datatype == 2 and bitpix == 8, (dims, datatype, bitpix)
x, y, z = dims[1:4]
data = nii[vox_offset : vox_offset + x * y * z]
assert len(data) == x * y * z
with open(out, "wb") as f:
    f.write(data)  # NIfTI stores x fastest, as RAW does
print(f"{out}: {x}x{y}x{z} u8")
