"""File I/O at the edge of the numerical core, one module per kind of file.

* :mod:`.raw` -- raw frames (camera raw files, 16-bit PNG/TIFF) and their sanity checks;
* :mod:`.dngread` -- uncompressed DNGs decoded directly (memory-mapped);
* :mod:`.exr` -- EXR channels and header;
* :mod:`.results` -- a merge result (:class:`~hdrcap.pipeline.result.HdrResult`) to and from
  its EXR or float DNG;
* :mod:`.dngwrite` -- the merge as a float CFA DNG; a raw file's colour metadata;
* :mod:`.emva_descriptor` -- EMVA 1288 descriptor files;
* :mod:`.files` -- atomic, no-clobber writes, hashes, readable-file checks.
"""
