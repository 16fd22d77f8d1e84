"""Paper sec. 4: the deformation metrics of Table 2 and the video metrics of Tables 1 and 3."""
