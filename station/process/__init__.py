"""Raw develop, masks and poses: a raw scan becomes a training-ready dataset."""
