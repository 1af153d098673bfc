"""Resource package (installed as ``rotcal_schemas``): the JSON table and metadata contracts."""
