raise ValueError("the controller has a bug")
