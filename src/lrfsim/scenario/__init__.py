"""The scenario: what a simulated recording depends on, as a file. Its sections (one pydantic model each), the
top-level model with the checks across sections, reading, validating and writing back a file, the memory a
scenario needs (with the servo's run time from its section alone), and the format as a Markdown page. The bottom
room of lrfsim: it imports no other room."""
