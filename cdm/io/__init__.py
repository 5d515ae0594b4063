"""Every file a user, a data set or a neighbour can write, read and written here alone (docs/security.md).

One module per kind; nothing is imported here, so a reader of JSON does not pay for torch.
"""
