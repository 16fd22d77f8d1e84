"""One object through the pipeline:  ``python -m flows.squeeze object=tomato``."""
from flows.evaluate import pipeline_main

main = pipeline_main("squeeze")

if __name__ == "__main__":
    main()
