"""Device protocols (sans-I/O codecs) and thin async transports (DESIGN §5).

- :mod:`drivers.base` — DecoderStats, the Decoder protocol, DriverError, the kind Registry.
- :mod:`drivers.hydrins` — the iXblue Hydrins INS: ``nmea`` (PHINS standard block + standard
  sentences, epoch assembler, encoders), ``stdbin`` (STDBIN V2–V5 decoder/encoder), ``nav`` (the
  canonical NavRecord both produce), ``timeofday`` (dating time-of-day tags).
- :mod:`drivers.zf` — the profiler: ``codec`` (Packet, Profile, the ProfileCodec seam), ``zfp1``
  (the ZFP1 stand-in format), ``assembler`` (ProfileAssembler with loss/reorder accounting).
- :mod:`drivers.pps` — PPS edges, gpsd's labelling rule, kernel / serial-line / udp sources.
- :mod:`drivers.can` — python-can buses from config, host-stamped frames, event markers.
- :mod:`drivers.transport.base` — async serial / udp / tcp transports yielding (bytes, host_ns).
- :mod:`drivers.capture.pcapng`, :mod:`drivers.capture.files` — captures and recorded files; :mod:`drivers.timing`
  — device clock drift/offset/jitter against receive stamps.
"""
