"""MCAP captures (docs/inputs.md, "MCAP captures"): ``reader`` (one capture
whole), ``stream`` (block by block), over ``fast`` (whole chunks decoded
into columns: ``chunks``, ``columns``, ``json_lines``) or ``messages``
(message by message), with ``records`` (the file's records and the limits
they are read within) and ``table`` (the table channel's messages as
labels); the ROS 2 message definitions (``ros2_msgdefs``) and their CDR
layouts (``ros2_cdr``); ``writer`` (captures as MCAP, for the simulator and
``rotcal apply``)."""
