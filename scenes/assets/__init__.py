"""The library's mesh objects and articulated fixtures, and the script that makes them."""
