"""Sessions: recording to HDF5 (:mod:`.recorder`), reading back (:mod:`.reader`), stitching whole-tissue maps
(:mod:`.stitch`), finding tumours and their depth (:mod:`.detect`), exporting (:mod:`.export`), and the
``review`` / ``stitch`` commands (:mod:`.cli`). Nothing here imports Qt except :mod:`.export`."""
