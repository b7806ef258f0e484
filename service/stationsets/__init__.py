"""Station-set files (``cellcal/stations@1``): the format (``format``) and the image
files it names (``images``)."""
