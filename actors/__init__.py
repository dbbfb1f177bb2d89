"""Acting: the one acting loop (``stepping``) and the actor process that runs it and publishes transitions."""
