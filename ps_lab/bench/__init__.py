"""The paper's experiments on rendered scenes and their report (``ps-lab bench paper``)."""
