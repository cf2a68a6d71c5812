"""Human proxies: policies behaviour-cloned from the 2019 human games (`behaviour_cloning`), fetched, fitted and
measured by `kitchen-humans` (`command`), then seated beside trained teams as partners no team trained with."""
