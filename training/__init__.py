"""dimenet.training: torch side of DIME-Net (BPnP layer, model, trainer). Imports the runtime, never the reverse."""
