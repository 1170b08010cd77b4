"""Files in and out: patient meshes and CT volumes, the one image reader, the format registry,
atomic writes, volume exports, and the JSON and HTML report."""
