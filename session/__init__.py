"""Sessions, without Qt: the HDF5 file format (:mod:`.format`), what a file says about itself (:mod:`.info`),
recording (:mod:`.writer`) and reading (:mod:`.reader`), whole-tissue maps (:mod:`.stitch`, and
:mod:`.live` while a session is under way), tumours and their depth (:mod:`.detect`), the one analysis
pipeline (:mod:`.analysis`) and its data exports (:mod:`.export`); :mod:`.synthetic` makes rows with the
real layouts for tests and benchmarks."""
