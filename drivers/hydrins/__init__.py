"""iXblue Hydrins INS protocols: NMEA (PHINS standard) and STDBIN, and the canonical NavRecord.

- ``nav`` — the canonical NavRecord both protocols produce; ``timeofday`` — dating time-of-day tags.
- ``nmea_sentences`` — typed sentence records, their field parsers, the checksum;
  ``nmea_decode`` — bytes → sentences (NmeaDecoder) → NavRecords per epoch (NmeaNavAssembler);
  ``nmea_encode`` — NavRecord → the PHINS standard block, ZDA, ``$PMLS,GPSUTC`` (for the emulators).
- ``stdbin_format`` — the STDBIN V2–V5 wire format: sizes, headers, block tables, checksum;
  ``stdbin_records`` — StdbinFrame / StdbinAnswer and the frame's NavRecord view;
  ``stdbin_decode`` — bytes → frames (StdbinDecoder) → NavRecords (StdbinNavDecoder);
  ``stdbin_encode`` — frames, answers and NavRecords → bytes (for the emulators).
"""
