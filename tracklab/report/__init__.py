"""What users read: results folders (``document``), tables (``tables``) and figures (``figures``;
``airborne``, ``servo``: those worlds' own), the sweep's and the tuning's folders (``sweep``,
``tuning``). Everything here reads statistics documents (dictionaries), never a world.
"""
