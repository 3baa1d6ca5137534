"""The one error every model loader raises for a weight file that cannot be used."""


class WeightsError(ValueError):
    """A weight file is missing, unreadable or does not fit the model: names the file, the tensor or
    key, and the shape expected against the shape found."""
