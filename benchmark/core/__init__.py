"""The kernel every layer stands on: the scene data model (:mod:`.scene`), the annotation data model
(:mod:`.annotation`), generator truth (:mod:`.truth`), the query protocol (:mod:`.protocol`), errors,
atomic writes, image I/O and memory measurement. It imports nothing else of the project."""
