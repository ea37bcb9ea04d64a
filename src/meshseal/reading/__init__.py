"""Reading pictures: loading them with their camera metadata (`pictures`), finding the object
(`framing`, `segmentation`), finding the camera (`registration`), predicting the original as the
picture shows it (`relight`, `footprint`), one picture's evidence under a method (`read`) and a
second look at a registered picture (`second_look`). Nothing here knows which scheme reads: the
scheme is a `methods.Method` handed in."""
