"""The base every other package stands on, importing nothing of the project: SE(2)/SE(3) geometry
(:mod:`core.geometry`), the scan type (:mod:`core.frame`), project errors (:mod:`core.errors`), atomic
output (:mod:`core.atomic`), C-grammar numbers and text lines of data files (:mod:`core.numbers`,
:mod:`core.textfile`) and YAML configuration (:mod:`core.yaml_config`)."""
