"""Files (layer 3): outputs, images, HDF5, image-set manifests, and (later) importers.

* :mod:`.outputs` — atomic output directories and files, provenance, JSON;
* :mod:`.images` — 8/16-bit PNG and TIFF;
* :mod:`.hdf5` — mapping, evaluation and reconstruction files;
* :mod:`.imageset` — image-set manifests (simulated or a real camera's images) and their
  decoding;
* :mod:`.heightmap` — height-map files (HDF5, NPY, CSV) of curved samples, and
  ``load_setup`` with them read.

Setup files are :mod:`pmdsim.setup.toml` (a setup's own serialisation).
May import: :mod:`pmdsim.errors`, :mod:`pmdsim.geometry`, :mod:`pmdsim.setup`,
:mod:`pmdsim.simulation`, :mod:`pmdsim.evaluation`, :mod:`pmdsim.calibration`.
"""

from .hdf5 import reconstructions_h5, write_evaluation_h5, write_mapping_h5, write_reconstructions_h5
from .images import read_image, write_png
from .outputs import (
    IMAGESET_FORMAT,
    MANIFEST_NAME,
    MAPPING_NAME,
    MARKER_NAME,
    atomic_file,
    atomic_output_dir,
    check_output_target,
    provenance,
    reused_output_dir,
    write_json,
)

__all__ = ["reconstructions_h5", "write_evaluation_h5", "write_mapping_h5", "write_reconstructions_h5", "read_image",
           "write_png", "IMAGESET_FORMAT", "MANIFEST_NAME", "MAPPING_NAME", "atomic_file", "atomic_output_dir",
           "provenance", "write_json", "MARKER_NAME", "check_output_target", "reused_output_dir"]
