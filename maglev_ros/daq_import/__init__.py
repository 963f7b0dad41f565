"""DAQ exports (CSV, NI TDMS, HDF5, MATLAB .mat, ASAM MDF4) into contract bags (``maglev-ros import``).

``spec.py`` reads the import spec (which file, which column is which contract channel, in what
unit), ``readers.py`` reads the columns of each format, ``timing.py`` checks a channel's time
(rate, gaps, duplicated or backwards stamps) and ``assemble.py`` builds the contract topics
(units to SI, position/speed completed, rates per topic checked) and writes the bag.
"""
from maglev_ros.daq_import.assemble import ImportResult, import_to_bag
from maglev_ros.daq_import.spec import ImportSpec, load_spec, spec_from_dict

__all__ = ["ImportResult", "ImportSpec", "import_to_bag", "load_spec", "spec_from_dict"]
