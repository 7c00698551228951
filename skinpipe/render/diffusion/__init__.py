"""Light under the skin: the fitted sum of Gaussians as blur terms, the blurs (direct and
recursive, and the switch between them), the pyramid layout, light across UV seams and
the layout's store on disk, and push-pull fill."""
