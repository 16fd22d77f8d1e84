"""Paper sec. 3.3, the secondary effect: diffusion components and masked generation, the weight-free physics
rendering of released material, prompts, and the 4D appearance refinement of eq. 7."""
