"""What prism-stream writes into every LAS header it makes: its own name, and the provenance record.

The LAS writers (:mod:`.las`, :mod:`.lasbuild`, :mod:`.copc`) share it.
"""

from __future__ import annotations

import json

import laspy

from .. import __version__

PROVENANCE_USER_ID = "prism-stream"
PROVENANCE_RECORD_ID = 1

SOFTWARE = f"prism-stream {__version__}"


def stamp(header) -> None:
    """What a LAS header says of the file itself: the generating software is prism-stream and its version (the
    inputs' own are in the provenance), the system identifier the LAS specification's word for points taken
    from other files, and the WKT bit the specification requires for point formats 6 to 10."""
    header.generating_software = SOFTWARE[:32]
    header.system_identifier = "EXTRACTION"
    if header.point_format.id >= 6:
        header.global_encoding.wkt = True


def provenance_vlr(provenance: dict) -> laspy.VLR:
    data = json.dumps(provenance, sort_keys=True).encode()
    if len(data) > 65535:
        slim = {k: v for k, v in provenance.items() if k != "sources"}
        slim["sources_omitted"] = len(provenance.get("sources", []))
        data = json.dumps(slim, sort_keys=True).encode()
    return laspy.VLR(PROVENANCE_USER_ID, PROVENANCE_RECORD_ID, "PRISM sampling provenance (JSON)", data)
