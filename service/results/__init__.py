"""The result document ``cellcal/result@1``: its schema (``schema``), the document built
and read back (``document``), the HTML report (``report``) and its plots (``plots``)."""
