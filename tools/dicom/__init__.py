"""The DICOM test and bench kit: synthetic radiographs (``synthetic``), a throwaway Orthanc on a free
loopback port (``orthanc``), and the timing of reading a header and pushing results (``bench``)."""
