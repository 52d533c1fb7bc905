"""Z+F profiler packets: the ProfileCodec seam, the ZFP1 stand-in format, profile reassembly."""
